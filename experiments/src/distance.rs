//! How far a locomotion task's body travelled in each episode of an experiment's runs.
//!
//! A return mixes progress with a survival bonus and control costs: an ant that stands still
//! with small actions earns about +1 per step, so a 1,000-step episode can return several
//! hundred without a step forward. The distance travelled, the integral of the root's forward
//! velocity over the episode (`Σ v · dt` over its stored transitions), is the figure that says
//! whether it walks. It is read from the planner's stored replay logs (read only, so this
//! works while the experiment runs).

use planner_service::persist::admin;
use planner_service::replay::{Record, TransitionRecord};
use proto::Builtin;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

/// One episode of one run.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeDistance {
    pub run: String,
    pub agent: String,
    pub episode: u32,
    pub steps: u32,
    /// The sum of the stored rewards.
    pub episode_return: f64,
    /// Metres travelled forward (negative: backwards).
    pub distance: f64,
    /// Seconds the episode lasted.
    pub seconds: f64,
}

/// Why the distances could not be read.
#[derive(Debug, thiserror::Error)]
pub enum DistanceError {
    #[error("task `{0}` does not move a body forward: no distance to measure")]
    NotLocomotion(String),
    #[error(transparent)]
    Admin(#[from] admin::AdminError),
}

/// Every episode of `records` (a run's replay log) with the distance its body travelled:
/// the forward velocity at index `velocity` of each next state, times `dt`, summed.
pub fn episode_distances(
    run: &str,
    records: &[Record],
    velocity: usize,
    dt: f64,
) -> Vec<EpisodeDistance> {
    let mut episodes: BTreeMap<(String, u32), EpisodeDistance> = BTreeMap::new();
    for record in records {
        let Record::Transition(TransitionRecord {
            agent,
            episode,
            next_obs,
            reward,
            ..
        }) = record
        else {
            continue;
        };
        let entry = episodes
            .entry((agent.clone(), *episode))
            .or_insert_with(|| EpisodeDistance {
                run: run.to_string(),
                agent: agent.clone(),
                episode: *episode,
                steps: 0,
                episode_return: 0.0,
                distance: 0.0,
                seconds: 0.0,
            });
        entry.steps += 1;
        entry.episode_return += f64::from(*reward);
        entry.distance += f64::from(next_obs.get(velocity).copied().unwrap_or(0.0)) * dt;
        entry.seconds += dt;
    }
    let mut rows: Vec<EpisodeDistance> = episodes.into_values().collect();
    rows.sort_by(|a, b| (a.episode, &a.agent).cmp(&(b.episode, &b.agent)));
    rows
}

/// The episodes of every run of `task` stored in an experiment folder's planner data
/// directory (`<folder>/planner`), by run name: the runs its daemon serves and the finished
/// ones a sitting archived.
pub fn experiment_distances(
    folder: &Path,
    task: Builtin,
) -> Result<Vec<EpisodeDistance>, DistanceError> {
    let velocity = task
        .forward_velocity()
        .ok_or_else(|| DistanceError::NotLocomotion(task.name().to_string()))?;
    let dt = task.spec().control_dt;
    let data_dir = folder.join("planner");
    let mut rows = Vec::new();
    for shelf in [admin::Shelf::Served, admin::Shelf::Archived] {
        for entry in admin::list_runs(&data_dir, shelf)? {
            if entry.spec.as_ref().is_some_and(|s| s.task == task.name()) {
                let records = admin::read_replay(&data_dir, shelf, &entry.name)?.records;
                rows.extend(episode_distances(&entry.name, &records, velocity, dt));
            }
        }
    }
    Ok(rows)
}

/// A Markdown table of the last `last` episodes of at least `min_steps` steps of each run.
pub fn markdown(rows: &[EpisodeDistance], last: usize, min_steps: u32) -> String {
    let mut out = String::from(
        "| run | episode | steps | return | forward distance (m) | mean forward velocity (m/s) |\n\
         |---|---:|---:|---:|---:|---:|\n",
    );
    let mut by_run: BTreeMap<&str, Vec<&EpisodeDistance>> = BTreeMap::new();
    for row in rows.iter().filter(|r| r.steps >= min_steps) {
        by_run.entry(&row.run).or_default().push(row);
    }
    for episodes in by_run.values() {
        for e in &episodes[episodes.len().saturating_sub(last)..] {
            let _ = writeln!(
                out,
                "| {} | {} | {} | {:.1} | {:.2} | {:.3} |",
                e.run,
                e.episode,
                e.steps,
                e.episode_return,
                e.distance,
                e.distance / e.seconds.max(f64::MIN_POSITIVE)
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use planner_service::replay::{ActionOrigin, HeaderRecord};

    fn step(agent: &str, episode: u32, velocity: f32, reward: f32) -> Record {
        let mut next_obs = vec![0.0; 27];
        next_obs[13] = velocity;
        Record::Transition(TransitionRecord {
            epoch: 1,
            agent: agent.into(),
            episode,
            step: 0,
            obs: vec![0.0; 27],
            act: vec![0.0; 8],
            origin: ActionOrigin::Planned,
            next_obs,
            reward,
        })
    }

    #[test]
    fn distance_is_the_forward_velocity_integrated_over_each_episode() {
        let records = vec![
            Record::Header(HeaderRecord {
                task: "ant".into(),
                obs_dim: 27,
                act_dim: 8,
            }),
            step("a", 0, 1.0, 1.0),
            step("a", 0, 3.0, 1.0),
            step("b", 0, -2.0, 0.5),
            step("a", 1, 0.5, 2.0),
        ];
        let velocity = Builtin::Ant.forward_velocity().unwrap();
        let rows = episode_distances("ant-x", &records, velocity, 0.05);
        assert_eq!(rows.len(), 3);
        assert_eq!((rows[0].agent.as_str(), rows[0].steps), ("a", 2));
        assert!((rows[0].distance - 0.2).abs() < 1e-9, "{rows:?}");
        assert!((rows[0].episode_return - 2.0).abs() < 1e-9);
        assert!((rows[1].distance + 0.1).abs() < 1e-9, "{rows:?}");
        assert_eq!((rows[2].episode, rows[2].steps), (1, 1));
        let table = markdown(&rows, 1, 2);
        assert!(
            table.contains("| ant-x | 0 | 2 | 2.0 | 0.20 | 2.000 |"),
            "{table}"
        );
        assert_eq!(table.lines().count(), 3, "one row of ≥ 2 steps: {table}");
        assert!(Builtin::Cartpole.forward_velocity().is_none());
    }

    /// Both the runs the daemon serves and the finished ones a sitting archived are read.
    #[test]
    fn an_experiments_served_and_archived_runs_are_both_measured() {
        use planner_service::persist::RunDir;
        use planner_service::replay::{ReplayLog, segments::LEGACY};
        use proto::{PlannerOverrides, RunSpec, TrainMode};
        let folder = tempfile::tempdir().unwrap();
        let data_dir = folder.path().join("planner");
        for (name, velocity) in [("ant-cem-s0", 1.0), ("ant-cem-s1", 2.0)] {
            let dir = RunDir::new(&data_dir, name);
            dir.write_spec(&RunSpec {
                task: "ant".into(),
                preset: None,
                overrides: PlannerOverrides::default(),
                mode: TrainMode::Sync,
                seed: 0,
                task_spec: None,
            })
            .unwrap();
            let records = [
                Record::Header(HeaderRecord {
                    task: "ant".into(),
                    obs_dim: 27,
                    act_dim: 8,
                }),
                step("a", 0, velocity, 1.0),
            ];
            ReplayLog::create_with(&dir.root().join(LEGACY), &records, |f| Box::new(f)).unwrap();
        }
        admin::archive_run(&data_dir, "ant-cem-s0").unwrap();
        let rows = experiment_distances(folder.path(), Builtin::Ant).unwrap();
        let runs: Vec<(&str, f64)> = rows.iter().map(|r| (r.run.as_str(), r.distance)).collect();
        let dt = Builtin::Ant.spec().control_dt;
        assert_eq!(runs.len(), 2, "{runs:?}");
        assert!(runs.contains(&("ant-cem-s1", 2.0 * dt)), "{runs:?}");
        assert!(runs.contains(&("ant-cem-s0", 1.0 * dt)), "{runs:?}");
    }
}
