//! A run's learned models, as one immutable snapshot.
//!
//! Planning reads a snapshot through an `Arc` while the trainer builds the next one from a
//! copy; the new snapshot is swapped in whole, so a plan never mixes models of two versions.

use crate::config::Preset;
use crate::dynamics::Ensemble;
use crate::energy::Regularizer;
use crate::plan::Learned;
use crate::reward::RewardModel;
use crate::termination::TerminationModel;
use proto::Task;
use rand::SeedableRng;
use rand::rngs::StdRng;

/// The dynamics model, the regulariser and (for a task whose reward or termination is learned)
/// the reward and termination models of one version.
#[derive(Clone, Debug)]
pub struct Models {
    /// 0 until the first training; +1 with every retraining.
    pub version: u64,
    /// Finished episodes whose transitions these models were trained on.
    pub episodes_covered: u32,
    pub dynamics: Ensemble,
    pub regularizer: Regularizer,
    /// The reward imagination scores with: `Some` exactly when the task's reward is learned
    /// ([`proto::Task::reward_is_learned`]); otherwise the task's own reward is used.
    pub reward: Option<RewardModel>,
    /// The termination imagination ends particles with: `Some` exactly when the task's
    /// termination is learned ([`proto::Task::termination_is_learned`]).
    pub termination: Option<TerminationModel>,
}

impl Models {
    /// Freshly initialised, untrained models of the preset's sizes.
    pub fn untrained(task: &'static Task, preset: &Preset, seed: u64) -> Self {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut dynamics = Ensemble::new(task, &preset.dynamics, &mut rng);
        let mut regularizer = Regularizer::new(
            preset.regularizer,
            &preset.energy,
            task.obs_dim,
            task.act_dim,
            &mut rng,
        );
        let mut reward = task
            .reward_is_learned()
            .then(|| RewardModel::new(task, &preset.reward, &preset.dynamics, &mut rng));
        dynamics.set_inference_precision(preset.inference_precision);
        regularizer.set_inference_precision(preset.inference_precision);
        if let Some(r) = &mut reward {
            r.set_inference_precision(preset.inference_precision);
        }
        let mut termination = task
            .termination_is_learned()
            .then(|| TerminationModel::new(task, &preset.dynamics, &mut rng));
        if let Some(t) = &mut termination {
            t.set_inference_precision(preset.inference_precision);
        }
        Self {
            version: 0,
            episodes_covered: 0,
            dynamics,
            regularizer,
            reward,
            termination,
        }
    }

    /// The learned parts of the task that imagination scores with (see [`Learned`]).
    pub fn learned(&self) -> Learned<'_> {
        Learned {
            reward: self.reward.as_ref(),
            termination: self.termination.as_ref(),
        }
    }

    /// Sets the number format every network plans in (see [`proto::InferencePrecision`]); the
    /// weights are packed for it on the next [`Models::pack_for_inference`] or first plan.
    pub fn set_inference_precision(&mut self, precision: proto::InferencePrecision) {
        self.dynamics.set_inference_precision(precision);
        self.regularizer.set_inference_precision(precision);
        if let Some(r) = &mut self.reward {
            r.set_inference_precision(precision);
        }
        if let Some(t) = &mut self.termination {
            t.set_inference_precision(precision);
        }
    }

    /// The kernel path of each network, for the status report (networks not yet packed show
    /// none: reading the path does not pack or measure).
    pub fn kernels(&self, precision: proto::InferencePrecision) -> RunKernels {
        let name = |p: Option<crate::nn::KernelPath>| p.map(|p| p.name().to_string());
        let energy = match &self.regularizer {
            Regularizer::None => None,
            Regularizer::Dae(m) => m.mlp().packed_kernel_path(),
            Regularizer::Deen(m) => m.mlp().packed_kernel_path(),
        };
        RunKernels {
            precision: precision.to_string(),
            dynamics: name(self.dynamics.member(0).mlp().packed_kernel_path()),
            energy: name(energy),
            reward: name(
                self.reward
                    .as_ref()
                    .and_then(|r| r.mlp().packed_kernel_path()),
            ),
        }
    }

    /// Packs every network's weights into the inference layout now, so that the first plan
    /// with these models neither pays for the packing nor allocates. The trainer calls it
    /// before a new version is swapped in.
    pub fn pack_for_inference(&self) {
        for i in 0..self.dynamics.members() {
            self.dynamics.member(i).mlp().pack_for_inference();
        }
        match &self.regularizer {
            Regularizer::None => {}
            Regularizer::Dae(m) => m.mlp().pack_for_inference(),
            Regularizer::Deen(m) => m.mlp().pack_for_inference(),
        }
        if let Some(r) = &self.reward {
            r.mlp().pack_for_inference();
        }
        if let Some(t) = &self.termination {
            t.mlp().pack_for_inference();
        }
    }

    /// The first part of these models that holds a NaN or an infinity (`None`: all finite).
    /// Models that fail this are never served or checkpointed.
    pub fn first_non_finite(&self) -> Option<String> {
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        for (i, m) in self.dynamics.parts().iter().enumerate() {
            let pieces: [(&str, &[f32]); 7] = [
                ("parameters", &m.params),
                ("input means", m.input_norm.mean()),
                ("input scales", m.input_norm.std()),
                ("target means", m.target_norm.mean()),
                ("target scales", m.target_norm.std()),
                ("maximum log-variances", &m.max_logvar),
                ("minimum log-variances", &m.min_logvar),
            ];
            if let Some((what, _)) = pieces.iter().find(|(_, v)| !finite(v)) {
                return Some(format!("dynamics member {i}: {what}"));
            }
        }
        if let Some(e) = self.regularizer.parts() {
            let pieces: [(&str, &[f32]); 3] = [
                ("parameters", &e.params),
                ("means", e.normalizer.mean()),
                ("scales", e.normalizer.std()),
            ];
            if let Some((what, _)) = pieces.iter().find(|(_, v)| !finite(v)) {
                return Some(format!("{} regulariser: {what}", self.regularizer.kind()));
            }
        }
        if let Some(t) = self.termination.as_ref().map(TerminationModel::parts) {
            let pieces: [(&str, &[f32]); 3] = [
                ("parameters", &t.params),
                ("input means", t.input_norm.mean()),
                ("input scales", t.input_norm.std()),
            ];
            if let Some((what, _)) = pieces.iter().find(|(_, v)| !finite(v)) {
                return Some(format!("termination model: {what}"));
            }
        }
        if let Some(r) = self.reward.as_ref().map(RewardModel::parts) {
            let pieces: [(&str, &[f32]); 4] = [
                ("parameters", &r.params),
                ("input means", r.input_norm.mean()),
                ("input scales", r.input_norm.std()),
                (
                    "reward mean and scale",
                    &[r.target_norm.mean()[0], r.target_norm.std()[0]],
                ),
            ];
            if let Some((what, _)) = pieces.iter().find(|(_, v)| !finite(v)) {
                return Some(format!("reward model: {what}"));
            }
        }
        None
    }

    /// Whether these models have been trained, every one a plan needs: a run explores with
    /// random actions until they are. For a task whose reward is learned that includes the
    /// reward model (a retraining whose time budget ran out before the reward model took a
    /// step leaves it untrained), so such a run never plans with a reward model of random
    /// weights.
    pub fn is_trained(&self) -> bool {
        self.version > 0 && self.reward.as_ref().is_none_or(RewardModel::is_trained)
    }
}

/// The kernel path each of a run's networks runs (`None`: not packed yet, or no such network).
#[derive(
    Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
pub struct RunKernels {
    /// The number format the run's preset asks for (`auto`, `bf16` or `f32`).
    pub precision: String,
    pub dynamics: Option<String>,
    pub energy: Option<String>,
    pub reward: Option<String>,
}
