//! Model checkpoints: one safetensors file per models version.
//!
//! The network weights are safetensors tensors (`dynamics.{member}`, `energy` and, for a task
//! whose reward or termination is learned, `reward` or `termination`; flat f32 in [`crate::nn::Mlp::params`] order);
//! everything small that a model also needs to predict — normaliser statistics, learned
//! log-variance bounds, the models version, the episodes the models were trained on, the
//! regulariser, whether the reward model is trained — is a JSON header stored in the safetensors
//! metadata under [`HEADER_KEY`]. One self-describing file per version means a checkpoint is
//! written with a single atomic rename and can be inspected with any safetensors reader.
//!
//! A CRC-32 of the JSON header and every tensor's bytes is stored in the metadata under
//! [`CHECKSUM_KEY`] and verified before anything is decoded, so a damaged file is an error
//! (and moved aside by [`crate::persist`]), never a model with a few wrong weights.

use crate::config::Preset;
use crate::dynamics::{Ensemble, ModelParts};
use crate::energy::{EnergyParts, Regularizer, RegularizerKind};
use crate::models::Models;
use crate::nn::Normalizer;
use crate::reward::{RewardModel, RewardParts};
use crate::termination::{TerminationModel, TerminationParts};
use proto::Task;
use safetensors::tensor::{Dtype, TensorView};
use safetensors::{SafeTensors, serialize};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// The safetensors metadata key that holds the JSON header.
pub const HEADER_KEY: &str = "ebmpc";

/// The safetensors metadata key that holds the checksum (decimal CRC-32).
pub const CHECKSUM_KEY: &str = "ebmpc.crc32";

/// Version of the checkpoint layout (not of the models); bumped when the header changes.
/// Version 2 added the checksum; version 1 files are refused as unsupported (not damaged), and
/// the run retrains from its replay log. Version 3 added the reward model (`reward` in the
/// header, the `reward` tensor); a version 2 file is read as models without one, which is
/// what it holds: no build that wrote version 2 could run a task whose reward is learned.
/// Version 4 added the termination model (`termination` in the header, the `termination`
/// tensor); older files are read as models without one, for the same reason.
pub const FORMAT_VERSION: u32 = 4;

/// The oldest layout this build reads (see [`FORMAT_VERSION`]).
pub const OLDEST_FORMAT_READ: u32 = 2;

/// Why a checkpoint could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("safetensors: {0}")]
    SafeTensors(#[from] safetensors::SafeTensorError),
    #[error("checkpoint header: {0}")]
    Header(#[from] serde_json::Error),
    #[error("checkpoint has no `{HEADER_KEY}` header")]
    MissingHeader,
    #[error(
        "checkpoint format {found} is not supported (this build reads {OLDEST_FORMAT_READ} to {FORMAT_VERSION})"
    )]
    Format { found: u32 },
    #[error("checkpoint is for {found}, the run learns {expected}")]
    Task { found: String, expected: String },
    #[error("checkpoint tensor `{name}`: {problem}")]
    Tensor { name: String, problem: String },
    #[error("checkpoint does not fit the run's preset: {0}")]
    Shape(#[from] crate::nn::ShapeError),
    #[error("checkpoint has no `{CHECKSUM_KEY}` checksum")]
    MissingChecksum,
    #[error("checkpoint checksum {stored} does not match its content ({computed})")]
    Checksum { stored: String, computed: u32 },
}

impl CheckpointError {
    /// Whether the file is damaged (as opposed to intact but not for this run or this build):
    /// damaged files are moved aside so that they are never tried again.
    pub fn is_damage(&self) -> bool {
        matches!(
            self,
            Self::SafeTensors(_)
                | Self::Header(_)
                | Self::MissingHeader
                | Self::MissingChecksum
                | Self::Checksum { .. }
        )
    }
}

/// The JSON header: everything but the weights.
#[derive(Debug, Serialize, Deserialize)]
struct Header {
    format: u32,
    /// The task's name (JSON: earlier builds wrote the catalog entry's name here too).
    task: String,
    models_version: u64,
    episodes_covered: u32,
    regularizer: RegularizerKind,
    dynamics: Vec<MemberStats>,
    energy: Option<Normalizer>,
    /// The reward model's statistics (absent in version 2 files and for a task whose reward
    /// is not learned).
    #[serde(default)]
    reward: Option<RewardStats>,
    /// The termination model's statistics (absent before version 4 and for a task whose
    /// termination is not learned).
    #[serde(default)]
    termination: Option<TerminationStats>,
}

/// The termination model's statistics and whether it has seen an end.
#[derive(Debug, Serialize, Deserialize)]
struct TerminationStats {
    input_norm: Normalizer,
    knows_ends: bool,
}

/// The reward model's statistics and whether it is trained.
#[derive(Debug, Serialize, Deserialize)]
struct RewardStats {
    input_norm: Normalizer,
    target_norm: Normalizer,
    trained: bool,
}

/// One dynamics member's statistics.
#[derive(Debug, Serialize, Deserialize)]
struct MemberStats {
    input_norm: Normalizer,
    target_norm: Normalizer,
    max_logvar: Vec<f32>,
    min_logvar: Vec<f32>,
}

fn dynamics_tensor(member: usize) -> String {
    format!("dynamics.{member}")
}

const ENERGY_TENSOR: &str = "energy";
const REWARD_TENSOR: &str = "reward";
const TERMINATION_TENSOR: &str = "termination";

/// Encodes `models` of `task` as safetensors bytes.
pub fn encode(models: &Models, task: &Task) -> Result<Vec<u8>, CheckpointError> {
    let members = models.dynamics.parts();
    let energy = models.regularizer.parts();
    let reward = models.reward.as_ref().map(RewardModel::parts);
    let termination = models.termination.as_ref().map(TerminationModel::parts);
    let header = Header {
        format: FORMAT_VERSION,
        task: task.name().to_string(),
        models_version: models.version,
        episodes_covered: models.episodes_covered,
        regularizer: models.regularizer.kind(),
        dynamics: members
            .iter()
            .map(|p| MemberStats {
                input_norm: p.input_norm.clone(),
                target_norm: p.target_norm.clone(),
                max_logvar: p.max_logvar.clone(),
                min_logvar: p.min_logvar.clone(),
            })
            .collect(),
        energy: energy.as_ref().map(|e| e.normalizer.clone()),
        reward: reward.as_ref().map(|r| RewardStats {
            input_norm: r.input_norm.clone(),
            target_norm: r.target_norm.clone(),
            trained: r.trained,
        }),
        termination: termination.as_ref().map(|t| TerminationStats {
            input_norm: t.input_norm.clone(),
            knows_ends: t.knows_ends,
        }),
    };
    let mut weights: Vec<(String, Vec<u8>, usize)> = members
        .iter()
        .enumerate()
        .map(|(i, p)| (dynamics_tensor(i), le_bytes(&p.params), p.params.len()))
        .collect();
    if let Some(e) = &energy {
        weights.push((
            ENERGY_TENSOR.to_string(),
            le_bytes(&e.params),
            e.params.len(),
        ));
    }
    if let Some(r) = &reward {
        weights.push((
            REWARD_TENSOR.to_string(),
            le_bytes(&r.params),
            r.params.len(),
        ));
    }
    if let Some(t) = &termination {
        weights.push((
            TERMINATION_TENSOR.to_string(),
            le_bytes(&t.params),
            t.params.len(),
        ));
    }
    let views = weights
        .iter()
        .map(|(name, bytes, len)| {
            Ok((
                name.as_str(),
                TensorView::new(Dtype::F32, vec![*len], bytes)?,
            ))
        })
        .collect::<Result<Vec<_>, safetensors::SafeTensorError>>()?;
    let header_json = serde_json::to_string(&header)?;
    let checksum = checksum(
        &header_json,
        weights
            .iter()
            .map(|(name, bytes, _)| (name.as_str(), bytes.as_slice())),
    );
    let metadata = HashMap::from([
        (HEADER_KEY.to_string(), header_json),
        (CHECKSUM_KEY.to_string(), checksum.to_string()),
    ]);
    Ok(serialize(views, Some(metadata))?)
}

/// CRC-32 of the JSON header and every tensor's bytes, tensors in name order.
fn checksum<'a>(header_json: &str, tensors: impl Iterator<Item = (&'a str, &'a [u8])>) -> u32 {
    let mut tensors: Vec<_> = tensors.collect();
    tensors.sort_by_key(|(name, _)| *name);
    let mut crc = crc32fast::Hasher::new();
    crc.update(header_json.as_bytes());
    for (name, bytes) in tensors {
        crc.update(name.as_bytes());
        crc.update(bytes);
    }
    crc.finalize()
}

/// Checks the stored checksum against the file's content.
fn verify(
    metadata: &HashMap<String, String>,
    header_json: &str,
    tensors: &SafeTensors<'_>,
) -> Result<(), CheckpointError> {
    let Some(stored) = metadata.get(CHECKSUM_KEY) else {
        // A file from before checksums is refused by its format version, not as damage.
        let header: Header = serde_json::from_str(header_json)?;
        return Err(if header.format < FORMAT_VERSION {
            CheckpointError::Format {
                found: header.format,
            }
        } else {
            CheckpointError::MissingChecksum
        });
    };
    let computed = checksum(
        header_json,
        tensors.iter().map(|(name, view)| (name, view.data())),
    );
    if stored.parse::<u32>().ok() != Some(computed) {
        return Err(CheckpointError::Checksum {
            stored: stored.clone(),
            computed,
        });
    }
    Ok(())
}

/// Decodes a checkpoint into models of the run's `preset` for `task`, checking every shape.
pub fn decode(
    bytes: &[u8],
    task: &'static Task,
    preset: &Preset,
) -> Result<Models, CheckpointError> {
    let (_, metadata) = SafeTensors::read_metadata(bytes)?;
    let metadata = metadata
        .metadata()
        .as_ref()
        .ok_or(CheckpointError::MissingHeader)?;
    let header_json = metadata
        .get(HEADER_KEY)
        .ok_or(CheckpointError::MissingHeader)?;
    let tensors = SafeTensors::deserialize(bytes)?;
    verify(metadata, header_json, &tensors)?;
    let header: Header = serde_json::from_str(header_json)?;
    if !(OLDEST_FORMAT_READ..=FORMAT_VERSION).contains(&header.format) {
        return Err(CheckpointError::Format {
            found: header.format,
        });
    }
    if header.task != task.name() {
        return Err(CheckpointError::Task {
            found: header.task,
            expected: task.name().to_string(),
        });
    }
    let parts = header
        .dynamics
        .into_iter()
        .enumerate()
        .map(|(i, stats)| {
            Ok(ModelParts {
                params: read_f32(&tensors, &dynamics_tensor(i))?,
                input_norm: stats.input_norm,
                target_norm: stats.target_norm,
                max_logvar: stats.max_logvar,
                min_logvar: stats.min_logvar,
            })
        })
        .collect::<Result<Vec<_>, CheckpointError>>()?;
    let dynamics = Ensemble::from_parts(task, &preset.dynamics, parts)?;
    let energy = match header.energy {
        None => None,
        Some(normalizer) => Some(EnergyParts {
            params: read_f32(&tensors, ENERGY_TENSOR)?,
            normalizer,
        }),
    };
    let regularizer = Regularizer::from_parts(
        header.regularizer,
        &preset.energy,
        task.obs_dim,
        task.act_dim,
        energy,
    )?;
    if regularizer.kind() != preset.regularizer {
        return Err(CheckpointError::Tensor {
            name: ENERGY_TENSOR.to_string(),
            problem: format!(
                "stored for regulariser {}, the run uses {}",
                regularizer.kind().name(),
                preset.regularizer.name()
            ),
        });
    }
    let reward = match (header.reward, task.reward_is_learned()) {
        (None, false) => None,
        (Some(stats), true) => Some(RewardModel::from_parts(
            task,
            &preset.reward,
            &preset.dynamics,
            RewardParts {
                params: read_f32(&tensors, REWARD_TENSOR)?,
                input_norm: stats.input_norm,
                target_norm: stats.target_norm,
                trained: stats.trained,
            },
        )?),
        (stored, learned) => {
            return Err(CheckpointError::Tensor {
                name: REWARD_TENSOR.to_string(),
                problem: format!(
                    "{} a reward model, the run's task {} a learned reward",
                    if stored.is_some() { "holds" } else { "lacks" },
                    if learned { "has" } else { "does not have" },
                ),
            });
        }
    };
    let termination = match (header.termination, task.termination_is_learned()) {
        (None, false) => None,
        (Some(stats), true) => Some(TerminationModel::from_parts(
            task,
            &preset.dynamics,
            TerminationParts {
                params: read_f32(&tensors, TERMINATION_TENSOR)?,
                input_norm: stats.input_norm,
                knows_ends: stats.knows_ends,
            },
        )?),
        (stored, learned) => {
            return Err(CheckpointError::Tensor {
                name: TERMINATION_TENSOR.to_string(),
                problem: format!(
                    "{} a termination model, the run's task {} a learned termination",
                    if stored.is_some() { "holds" } else { "lacks" },
                    if learned { "has" } else { "does not have" },
                ),
            });
        }
    };
    Ok(Models {
        version: header.models_version,
        episodes_covered: header.episodes_covered,
        dynamics,
        regularizer,
        reward,
        termination,
    })
}

fn le_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn read_f32(tensors: &SafeTensors<'_>, name: &str) -> Result<Vec<f32>, CheckpointError> {
    let problem = |problem: String| CheckpointError::Tensor {
        name: name.to_string(),
        problem,
    };
    let view = tensors
        .tensor(name)
        .map_err(|e| problem(format!("missing ({e})")))?;
    if view.dtype() != Dtype::F32 {
        return Err(problem(format!("dtype {:?}, expected F32", view.dtype())));
    }
    Ok(view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Transitions;
    use proto::Builtin;
    use rand::SeedableRng;
    use rand::rngs::StdRng;

    fn trained(method: &str) -> (Preset, Models) {
        trained_for(Builtin::Cartpole.task(), method)
    }

    /// Cartpole with its reward observed only.
    fn learned_cartpole() -> &'static Task {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "learned-cartpole".into();
        spec.reward = proto::task::RewardKind::Learned;
        Task::intern(spec, &proto::task::SpecBounds::default()).unwrap()
    }

    fn trained_for(task: &'static Task, method: &str) -> (Preset, Models) {
        let mut preset = Preset::new(task, Some(method)).unwrap();
        preset.dynamics.hidden_size = 8;
        preset.dynamics.ensemble_size = preset.dynamics.ensemble_size.min(2);
        preset.energy.hidden_size = 8;
        preset.reward.hidden_size = 8;
        let mut models = Models::untrained(task, &preset, 3);
        let mut data = Transitions::new(task.obs_dim, task.act_dim);
        for i in 0..40 {
            let s = [i as f32 * 0.1, 0.2, -0.1, 0.05 * i as f32];
            data.push(&s, &[0.5], 0.1 * i as f32, &[s[0] + 0.01, 0.2, -0.1, s[3]]);
            if i % 10 == 9 {
                data.mark_terminated(data.len() - 1);
            }
        }
        let mut rng = StdRng::seed_from_u64(1);
        models.dynamics.fit(&data, 2, &mut rng);
        models.regularizer.fit(&data, 2, &mut rng);
        if let Some(reward) = &mut models.reward {
            reward.fit(&data, 2, &mut rng);
        }
        if let Some(termination) = &mut models.termination {
            termination.fit(&data, 2, &mut rng);
        }
        models.version = 4;
        models.episodes_covered = 7;
        (preset, models)
    }

    #[test]
    fn a_learned_reward_model_round_trips_and_must_match_the_task() {
        let task = learned_cartpole();
        let (preset, models) = trained_for(task, "cem+deen");
        let bytes = encode(&models, task).unwrap();
        let restored = decode(&bytes, task, &preset).unwrap();
        let (saved, loaded) = (models.reward.unwrap(), restored.reward.unwrap());
        assert!(loaded.is_trained());
        assert_eq!(loaded.parts(), saved.parts());
        // Another size of reward network does not fit.
        let mut wider = preset.clone();
        wider.reward.hidden_size = 9;
        let err = decode(&bytes, task, &wider).unwrap_err();
        assert!(err.to_string().contains("reward parameters"), "{err}");
        // Models without a reward model do not serve a learned reward, nor the reverse.
        let (_, plain) = trained("cem+deen");
        let mut renamed = encode(&plain, Builtin::Cartpole.task()).unwrap();
        renamed = rewrite_header(&renamed, |h| h["task"] = task.name().into());
        let err = decode(&renamed, task, &preset).unwrap_err();
        assert!(err.to_string().contains("lacks a reward model"), "{err}");
        let back = rewrite_header(&bytes, |h| h["task"] = "cartpole".into());
        let plain_preset = Preset {
            task: Builtin::Cartpole.task(),
            ..preset.clone()
        };
        let err = decode(&back, Builtin::Cartpole.task(), &plain_preset).unwrap_err();
        assert!(err.to_string().contains("holds a reward model"), "{err}");
    }

    #[test]
    fn a_learned_termination_model_round_trips_and_must_match_the_task() {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "learned-end-cartpole".into();
        spec.termination = proto::task::TerminationKind::Learned;
        let task = Task::intern(spec, &proto::task::SpecBounds::default()).unwrap();
        let (preset, models) = trained_for(task, "cem+deen");
        let saved = models.termination.clone().unwrap();
        assert!(saved.knows_ends());
        let bytes = encode(&models, task).unwrap();
        let restored = decode(&bytes, task, &preset).unwrap();
        assert_eq!(restored.termination.unwrap().parts(), saved.parts());
        // Models without a termination model do not serve a learned termination.
        let (_, plain) = trained("cem+deen");
        let renamed = rewrite_header(&encode(&plain, Builtin::Cartpole.task()).unwrap(), |h| {
            h["task"] = task.name().into()
        });
        let err = decode(&renamed, task, &preset).unwrap_err();
        assert!(
            err.to_string().contains("lacks a termination model"),
            "{err}"
        );
    }

    /// The checkpoint `bytes` with its JSON header edited by `edit`, checksummed again.
    fn rewrite_header(bytes: &[u8], edit: impl FnOnce(&mut serde_json::Value)) -> Vec<u8> {
        let (_, metadata) = SafeTensors::read_metadata(bytes).unwrap();
        let mut header: serde_json::Value =
            serde_json::from_str(&metadata.metadata().as_ref().unwrap()[HEADER_KEY]).unwrap();
        edit(&mut header);
        let header = header.to_string();
        let tensors = SafeTensors::deserialize(bytes).unwrap();
        let views: Vec<(String, TensorView<'_>)> = tensors.tensors();
        let crc = checksum(&header, views.iter().map(|(n, v)| (n.as_str(), v.data())));
        serialize(
            views,
            Some(HashMap::from([
                (HEADER_KEY.to_string(), header),
                (CHECKSUM_KEY.to_string(), crc.to_string()),
            ])),
        )
        .unwrap()
    }

    /// A version 2 file (before reward models) still loads: it holds models without one.
    #[test]
    fn a_version_2_checkpoint_reads_as_models_without_a_reward_model() {
        let (preset, models) = trained("cem+deen");
        let task = Builtin::Cartpole.task();
        let bytes = encode(&models, task).unwrap();
        let v2 = rewrite_header(&bytes, |h| {
            h["format"] = 2.into();
            h.as_object_mut().unwrap().remove("reward");
        });
        let restored = decode(&v2, task, &preset).unwrap();
        assert!(restored.reward.is_none());
        assert_eq!(restored.dynamics.parts(), models.dynamics.parts());
        let v4 = rewrite_header(&bytes, |h| h["format"] = (FORMAT_VERSION + 1).into());
        let err = decode(&v4, task, &preset).unwrap_err();
        assert!(matches!(err, CheckpointError::Format { .. }), "{err}");
    }

    #[test]
    fn a_decoded_checkpoint_predicts_exactly_what_was_saved() {
        for method in ["cem", "cem+dae", "pets+deen"] {
            let (preset, models) = trained(method);
            let task = Builtin::Cartpole.task();
            let bytes = encode(&models, Builtin::Cartpole.task()).unwrap();
            let restored = decode(&bytes, task, &preset).unwrap();
            assert_eq!(restored.version, 4);
            assert_eq!(restored.episodes_covered, 7);
            assert_eq!(
                restored.dynamics.parts(),
                models.dynamics.parts(),
                "{method}"
            );
            assert_eq!(
                restored.regularizer.parts(),
                models.regularizer.parts(),
                "{method}"
            );
            assert_eq!(restored.regularizer.kind(), preset.regularizer);
        }
    }

    #[test]
    fn a_checkpoint_that_does_not_fit_the_run_is_refused() {
        let (preset, models) = trained("cem+deen");
        let bytes = encode(&models, Builtin::Cartpole.task()).unwrap();
        let err = decode(&bytes, Builtin::Ant.task(), &preset).unwrap_err();
        assert!(matches!(err, CheckpointError::Task { .. }), "{err}");
        let mut wider = preset.clone();
        wider.dynamics.hidden_size = 16;
        let err = decode(&bytes, Builtin::Cartpole.task(), &wider).unwrap_err();
        assert!(matches!(err, CheckpointError::Shape(_)), "{err}");
        let mut other = preset.clone();
        other.regularizer = RegularizerKind::Dae;
        assert!(decode(&bytes, Builtin::Cartpole.task(), &other).is_err());
    }

    #[test]
    fn damaged_bytes_are_an_error_not_a_panic() {
        let (preset, models) = trained("cem+deen");
        let bytes = encode(&models, Builtin::Cartpole.task()).unwrap();
        let task = Builtin::Cartpole.task();
        for cut in [0, 7, 8, 100, bytes.len() / 2, bytes.len() - 1] {
            assert!(
                decode(&bytes[..cut], task, &preset).is_err(),
                "cut at {cut}"
            );
        }
        // Every byte flipped in turn: each is refused as damage, none decodes.
        for at in 0..bytes.len() {
            let mut flipped = bytes.clone();
            flipped[at] ^= 0x01;
            match decode(&flipped, task, &preset) {
                Ok(_) => panic!("a flipped bit at byte {at} was loaded"),
                Err(e) => assert!(
                    e.is_damage() || matches!(e, CheckpointError::Format { .. }),
                    "byte {at}: {e}"
                ),
            }
        }
    }

    #[test]
    fn a_checkpoint_from_before_checksums_is_unsupported_not_damaged() {
        let (preset, models) = trained("cem");
        let bytes = encode(&models, Builtin::Cartpole.task()).unwrap();
        let (_, metadata) = SafeTensors::read_metadata(&bytes).unwrap();
        let mut header: serde_json::Value =
            serde_json::from_str(&metadata.metadata().as_ref().unwrap()[HEADER_KEY]).unwrap();
        header["format"] = 1.into();
        let tensors = SafeTensors::deserialize(&bytes).unwrap();
        let views: Vec<(String, TensorView<'_>)> = tensors.tensors();
        let old = serialize(
            views,
            Some(HashMap::from([(
                HEADER_KEY.to_string(),
                header.to_string(),
            )])),
        )
        .unwrap();
        let err = decode(&old, Builtin::Cartpole.task(), &preset).unwrap_err();
        assert!(matches!(err, CheckpointError::Format { found: 1 }), "{err}");
        assert!(!err.is_damage());
    }
}
