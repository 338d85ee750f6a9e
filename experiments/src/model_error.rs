//! How wrong a stored run's models are, region by region: `ebmpc-experiment model-error`.
//!
//! A planner is drawn to wherever its model promises more than reality pays, and the
//! regulariser is there to hold it back where the data are thin. When a learning curve falls
//! (a half-cheetah that starts to rear and then flips), the questions are whether the models
//! were over-optimistic in the states it went to, and whether the energy saw those transitions
//! as unfamiliar. This answers them from what a run stored, without planning: every stored
//! transition `(s, a, s')` goes through the run's newest models, which predict the next
//! observation `ŝ'` from the real `(s, a)`. Per episode and per interval of one observation
//! (the cheetah's pitch, say) it reports
//!
//! - the RMSE of `ŝ'` against `s'` over every observation dimension (raw units);
//! - the reward error, `r(s, a, ŝ') − r(s, a, s')`: positive is over-optimistic, what the
//!   planner would gain by going there that reality does not pay (one step; a plan compounds
//!   it over its horizon);
//! - the regulariser's energy of the real transition and of the imagined one (the penalty
//!   per step is `α` times the latter).
//!
//! An ensemble's prediction is the mean of its members' means. Episodes that finished after the
//! checkpoint's `episodes_covered` ones were not trained on: those rows are marked held out,
//! the only ones that say how the models generalise.

use crate::stored_run::{self, StoredRun};
use anyhow::{Result, bail};
use planner_service::energy::RegularizerKind;
use planner_service::replay::{Record, TransitionRecord, segments};
use proto::{Builtin, EpisodeEnd};
use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::PathBuf;

/// Transitions pushed through the models at once.
const BATCH: usize = 512;

/// What to measure.
#[derive(Clone, Debug)]
pub struct ModelErrorConfig {
    /// A run's directory: `run.json`, `models-*.safetensors` and `replay/` (see
    /// [`crate::stored_run`]).
    pub run_dir: PathBuf,
    /// Group each episode's transitions by this observation of `s` (`None`: one group).
    pub by_obs: Option<usize>,
    /// Ascending edges of the groups on that observation: `n` edges make `n + 1` intervals.
    pub edges: Vec<f32>,
    /// Only these episodes (`None`: every episode).
    pub episodes: Option<Vec<u32>>,
}

/// One episode's transitions in one interval of the grouping observation.
#[derive(Clone, Debug, PartialEq)]
pub struct ErrorRow {
    pub episode: u32,
    /// Whether the models certainly never trained on the episode (see the module doc).
    pub held_out: bool,
    /// Index of the interval (0 below the first edge).
    pub interval: usize,
    pub transitions: usize,
    /// Root-mean-square error of the predicted next observation, over transitions and
    /// dimensions.
    pub next_obs_rmse: f64,
    /// Mean of `r(s, a, ŝ') − r(s, a, s')`.
    pub reward_error_mean: f64,
    /// Root-mean-square of the same.
    pub reward_error_rms: f64,
    /// Mean energy of the real transitions (`None` without a regulariser).
    pub energy_real: Option<f64>,
    /// Mean energy of the imagined transitions `(s, a, ŝ')`.
    pub energy_imagined: Option<f64>,
}

/// The rows of a run, with what they were measured with.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelErrorReport {
    pub task: Builtin,
    pub models_version: u64,
    pub episodes_covered: u32,
    pub by_obs: Option<usize>,
    pub edges: Vec<f32>,
    /// Sorted by episode, then interval.
    pub rows: Vec<ErrorRow>,
}

/// Sums of one (episode, interval) group.
#[derive(Default)]
struct Sums {
    transitions: usize,
    squared_obs_error: f64,
    reward_error: f64,
    squared_reward_error: f64,
    energy_real: f64,
    energy_imagined: f64,
}

/// The interval of `value` among ascending `edges` (a value on an edge belongs above it).
pub fn interval(value: f32, edges: &[f32]) -> usize {
    edges.partition_point(|&edge| edge <= value)
}

/// The label of interval `i` of observation `obs` among `edges`.
pub fn interval_label(obs: usize, i: usize, edges: &[f32]) -> String {
    match (i.checked_sub(1).map(|j| edges[j]), edges.get(i)) {
        (None, None) => "all".to_string(),
        (None, Some(hi)) => format!("obs_{obs} < {hi}"),
        (Some(lo), None) => format!("obs_{obs} ≥ {lo}"),
        (Some(lo), Some(hi)) => format!("{lo} ≤ obs_{obs} < {hi}"),
    }
}

/// Loads the run and measures its newest models on its stored transitions.
pub fn run(config: &ModelErrorConfig) -> Result<ModelErrorReport> {
    if !config.edges.windows(2).all(|w| w[0] < w[1]) || config.edges.iter().any(|e| !e.is_finite())
    {
        bail!("the edges must be finite and strictly ascending");
    }
    if config.by_obs.is_none() && !config.edges.is_empty() {
        bail!("edges need an observation to group by (--by-obs)");
    }
    let StoredRun {
        dir, task, models, ..
    } = stored_run::load(&config.run_dir)?;
    let spec = task.task();
    if spec.reward_is_learned() {
        bail!("{task}'s reward is learned: there is no reward formula to compare with");
    }
    let (o, a) = (spec.obs_dim, spec.act_dim);
    if let Some(k) = config.by_obs.filter(|&k| k >= o) {
        bail!("{task} has {o} observations: --by-obs {k} is out of range");
    }
    let records = segments::read(dir.root())?.recovered.records;
    let held_out = held_out_episodes(&records, models.episodes_covered);
    let wanted = |t: &TransitionRecord| {
        config
            .episodes
            .as_ref()
            .is_none_or(|list| list.contains(&t.episode))
    };
    let selected: Vec<&TransitionRecord> = records
        .iter()
        .filter_map(|record| match record {
            Record::Transition(t) if wanted(t) => Some(t),
            _ => None,
        })
        .collect();
    if selected.is_empty() {
        bail!("the run holds no transition of the episodes asked for");
    }

    let with_energy = models.regularizer.kind() != RegularizerKind::None;
    let members = models.dynamics.members();
    let mut dynamics_scratch = models.dynamics.scratch(BATCH);
    let mut energy_scratch = models.regularizer.scratch(BATCH);
    let mut groups: BTreeMap<(u32, usize), Sums> = BTreeMap::new();
    let (mut obs, mut act, mut next) = (Vec::new(), Vec::new(), Vec::new());
    let mut member_next = vec![0.0f32; BATCH * o];
    let mut predicted = vec![0.0f32; BATCH * o];
    let (mut energy_real, mut energy_imagined) = (vec![0.0f32; BATCH], vec![0.0f32; BATCH]);
    for chunk in selected.chunks(BATCH) {
        let rows = chunk.len();
        obs.clear();
        act.clear();
        next.clear();
        for t in chunk {
            obs.extend_from_slice(&t.obs);
            act.extend_from_slice(&t.act);
            next.extend_from_slice(&t.next_obs);
        }
        predicted[..rows * o].fill(0.0);
        for m in 0..members {
            models.dynamics.predict_next(
                m,
                &obs,
                &act,
                rows,
                &mut dynamics_scratch,
                None,
                &mut member_next[..rows * o],
            );
            for (p, q) in predicted.iter_mut().zip(&member_next[..rows * o]) {
                *p += q / members as f32;
            }
        }
        if with_energy {
            let regularizer = &models.regularizer;
            let scratch = &mut energy_scratch;
            regularizer.energy(&obs, &act, &next, rows, scratch, &mut energy_real);
            let imagined = &predicted[..rows * o];
            regularizer.energy(&obs, &act, imagined, rows, scratch, &mut energy_imagined);
        }
        for (i, t) in chunk.iter().enumerate() {
            let s = &obs[i * o..(i + 1) * o];
            let u = &act[i * a..(i + 1) * a];
            let (real, imagined) = (&next[i * o..(i + 1) * o], &predicted[i * o..(i + 1) * o]);
            let group = config.by_obs.map_or(0, |k| interval(s[k], &config.edges));
            let sums = groups.entry((t.episode, group)).or_default();
            sums.transitions += 1;
            sums.squared_obs_error += real
                .iter()
                .zip(imagined)
                .map(|(x, y)| f64::from(y - x).powi(2))
                .sum::<f64>();
            let error = f64::from(spec.reward(s, u, imagined) - spec.reward(s, u, real));
            sums.reward_error += error;
            sums.squared_reward_error += error * error;
            sums.energy_real += f64::from(energy_real[i]);
            sums.energy_imagined += f64::from(energy_imagined[i]);
        }
    }
    let rows = groups
        .into_iter()
        .map(|((episode, interval), s)| {
            let n = s.transitions as f64;
            ErrorRow {
                episode,
                held_out: held_out.contains(&episode),
                interval,
                transitions: s.transitions,
                next_obs_rmse: (s.squared_obs_error / (n * o as f64)).sqrt(),
                reward_error_mean: s.reward_error / n,
                reward_error_rms: (s.squared_reward_error / n).sqrt(),
                energy_real: with_energy.then(|| s.energy_real / n),
                energy_imagined: with_energy.then(|| s.energy_imagined / n),
            }
        })
        .collect();
    Ok(ModelErrorReport {
        task,
        models_version: models.version,
        episodes_covered: models.episodes_covered,
        by_obs: config.by_obs,
        edges: config.edges.clone(),
        rows,
    })
}

/// The episodes of `records` (a run's replay, in order) that the models, trained on `covered`
/// finished episodes, certainly never saw: those that finished after them (later in the order
/// of the episodes' ends). An interrupted episode is never counted as held out: the retraining
/// that follows a resume sees it without counting it. In a run that retrains during episodes
/// (asynchronous training) even a later episode may have been seen in part; the experiments
/// retrain between episodes.
fn held_out_episodes(records: &[Record], covered: u32) -> BTreeSet<u32> {
    records
        .iter()
        .filter_map(|record| match record {
            Record::EpisodeEnd(end) if end.end != EpisodeEnd::Interrupted => Some(end.episode),
            _ => None,
        })
        .skip(covered as usize)
        .collect()
}

impl ModelErrorReport {
    /// A Markdown table of the rows, under a line that says which models measured them.
    pub fn markdown(&self) -> String {
        let mut out = format!(
            "{} models v{} (trained on {} finished episodes); \
             reward error = r(s, a, ŝ') − r(s, a, s')\n\n",
            self.task, self.models_version, self.episodes_covered
        );
        out.push_str(
            "| episode | held out | states | transitions | next-obs RMSE | reward error mean | \
             reward error RMS | energy (real) | energy (imagined) |\n\
             |---:|---|---|---:|---:|---:|---:|---:|---:|\n",
        );
        let energy = |e: Option<f64>| e.map_or("—".to_string(), |e| format!("{e:.3}"));
        for r in &self.rows {
            let states = self.by_obs.map_or("all".to_string(), |k| {
                interval_label(k, r.interval, &self.edges)
            });
            let _ = writeln!(
                out,
                "| {} | {} | {} | {} | {:.3} | {:+.3} | {:.3} | {} | {} |",
                r.episode,
                if r.held_out { "yes" } else { "no" },
                states,
                r.transitions,
                r.next_obs_rmse,
                r.reward_error_mean,
                r.reward_error_rms,
                energy(r.energy_real),
                energy(r.energy_imagined),
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stored_run::store_tiny_cartpole_run;
    use planner_service::replay::segments::LEGACY;
    use planner_service::replay::{
        ActionOrigin, EpisodeEndRecord, HeaderRecord, ReplayLog, TransitionRecord,
    };

    #[test]
    fn intervals_split_at_ascending_edges_and_say_so() {
        let edges = [-1.0, 0.5];
        assert_eq!(interval(-2.0, &edges), 0);
        assert_eq!(
            interval(-1.0, &edges),
            1,
            "an edge belongs to the interval above"
        );
        assert_eq!(interval(0.0, &edges), 1);
        assert_eq!(interval(0.5, &edges), 2);
        assert_eq!(interval_label(2, 0, &edges), "obs_2 < -1");
        assert_eq!(interval_label(2, 1, &edges), "-1 ≤ obs_2 < 0.5");
        assert_eq!(interval_label(2, 2, &edges), "obs_2 ≥ 0.5");
        assert_eq!(interval_label(2, 0, &[]), "all");
    }

    fn transition(episode: u32, obs: Vec<f32>, act: Vec<f32>, next_obs: Vec<f32>) -> Record {
        Record::Transition(TransitionRecord {
            epoch: 1,
            agent: "a".into(),
            episode,
            step: 0,
            obs,
            act,
            origin: ActionOrigin::Planned,
            next_obs,
            reward: 0.0,
        })
    }

    fn end(episode: u32, how: EpisodeEnd) -> Record {
        Record::EpisodeEnd(EpisodeEndRecord {
            epoch: 1,
            agent: "a".into(),
            episode,
            steps: 1,
            episode_return: 0.0,
            end: how,
        })
    }

    /// A stored cartpole run whose replay holds, for episodes 0–2, transitions whose next
    /// observation is exactly what its models predict, except in episode 2, where states with
    /// `x ≥ 0` land `delta` further along `x` than predicted. The models were trained on one
    /// finished episode: episode 0. Episode 1 was interrupted (a retraining at a resume may
    /// have seen it), so only episode 2 is held out.
    fn stored_run_with_replay(delta: f32) -> (tempfile::TempDir, PathBuf) {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("run");
        store_tiny_cartpole_run(&dir);
        let mut stored = stored_run::load(&dir).unwrap();
        stored.models.episodes_covered = 1;
        let task = stored.task.task();
        stored.dir.save_models(1, &stored.models, task).unwrap();

        let mut scratch = stored.models.dynamics.scratch(1);
        let mut records = vec![Record::Header(HeaderRecord {
            task: "cartpole".into(),
            obs_dim: 4,
            act_dim: 1,
        })];
        for episode in 0..3u32 {
            for k in 0..6 {
                let x = -0.5 + 0.2 * k as f32;
                let obs = vec![x, 0.3, 0.1 * k as f32, -0.2];
                let act = vec![0.5 - 0.1 * k as f32];
                let mut next = vec![0.0; 4];
                stored.models.dynamics.predict_next(
                    0,
                    &obs,
                    &act,
                    1,
                    &mut scratch,
                    None,
                    &mut next,
                );
                if episode == 2 && x >= 0.0 {
                    next[0] += delta;
                }
                records.push(transition(episode, obs, act, next));
            }
            let how = if episode == 1 {
                EpisodeEnd::Interrupted
            } else {
                EpisodeEnd::TimeLimit
            };
            records.push(end(episode, how));
        }
        ReplayLog::create_with(&dir.join(LEGACY), &records, |f| Box::new(f)).unwrap();
        (tmp, dir)
    }

    #[test]
    fn errors_show_where_reality_left_the_models_and_which_episodes_were_held_out() {
        let delta = 0.3f32;
        let (_tmp, dir) = stored_run_with_replay(delta);
        let report = run(&ModelErrorConfig {
            run_dir: dir.clone(),
            by_obs: Some(0),
            edges: vec![0.0],
            episodes: None,
        })
        .unwrap();
        assert_eq!(
            (report.task, report.episodes_covered),
            (Builtin::Cartpole, 1)
        );
        // Three episodes × two intervals (x < 0: three states, x ≥ 0: three).
        assert_eq!(report.rows.len(), 6, "{}", report.markdown());
        for r in &report.rows {
            assert_eq!(r.transitions, 3);
            assert_eq!(r.held_out, r.episode == 2, "{r:?}");
            assert!(r.energy_real.is_some() && r.energy_imagined.is_some());
            if r.episode == 2 && r.interval == 1 {
                // One of four dimensions off by δ in every transition.
                let expected = f64::from(delta) / 2.0;
                assert!((r.next_obs_rmse - expected).abs() < 1e-4, "{r:?}");
                assert!(
                    r.reward_error_rms > 1e-3,
                    "moving the cart changes the reward"
                );
                assert_ne!(r.energy_real, r.energy_imagined);
            } else {
                assert!(r.next_obs_rmse < 1e-5, "{r:?}");
                assert!(r.reward_error_rms < 1e-5, "{r:?}");
                let (real, imagined) = (r.energy_real.unwrap(), r.energy_imagined.unwrap());
                assert!((real - imagined).abs() < 1e-4, "{r:?}");
            }
        }
        let table = report.markdown();
        assert!(
            table.contains("| 2 | yes | obs_0 ≥ 0 | 3 | 0.150 |"),
            "{table}"
        );
        assert!(
            table.contains("| 0 | no | obs_0 < 0 | 3 | 0.000 |"),
            "{table}"
        );

        let only = run(&ModelErrorConfig {
            run_dir: dir,
            by_obs: None,
            edges: vec![],
            episodes: Some(vec![2]),
        })
        .unwrap();
        assert_eq!(only.rows.len(), 1);
        assert_eq!((only.rows[0].episode, only.rows[0].transitions), (2, 6));
        let expected = (f64::from(delta).powi(2) * 3.0 / 24.0).sqrt();
        assert!((only.rows[0].next_obs_rmse - expected).abs() < 1e-4);
    }

    #[test]
    fn refuses_what_it_cannot_measure() {
        let (_tmp, dir) = stored_run_with_replay(0.1);
        let config = |by_obs, edges: Vec<f32>, episodes| ModelErrorConfig {
            run_dir: dir.clone(),
            by_obs,
            edges,
            episodes,
        };
        for (bad, says) in [
            (config(Some(0), vec![0.5, 0.1], None), "ascending"),
            (config(Some(0), vec![f32::NAN], None), "finite"),
            (config(None, vec![0.0], None), "--by-obs"),
            (config(Some(4), vec![], None), "out of range"),
            (config(None, vec![], Some(vec![7])), "no transition"),
        ] {
            let err = run(&bad).unwrap_err().to_string();
            assert!(err.contains(says), "{bad:?}: {err}");
        }
    }
}
