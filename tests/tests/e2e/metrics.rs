//! The metrics endpoint: scraped with a real HTTP client while an agent plays, it serves every
//! metric the daemon keeps, its counters move as the agent's plans and refusals happen, and
//! the status report carries the same figures.

use ebmpc_e2e::client::{Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir, free_port};
use proto::{Builtin, EpisodeEnd, Observation, RunSpec};

const PLANNER: &str = "metrics";

/// Every metric the issue names, as served: plan latency per run, iterations, cut plans,
/// misses, refusals by code, wildcards dropped, models version, replay transitions and bytes,
/// episodes, agents, queue depth per agent, fsync latency, training duration and losses; and
/// how often plans stepped back for a more urgent one; how retrainings fare against plans
/// (their share, slices, waits, and whether one is starving); dormant stored runs.
const METRICS: [&str; 21] = [
    "ebmpc_plan_seconds_bucket",
    "ebmpc_plan_iterations_bucket",
    "ebmpc_plans_cut_total",
    "ebmpc_deadline_misses_total",
    "ebmpc_plan_step_backs_total",
    "ebmpc_refused_messages_total",
    "ebmpc_wildcard_keys_dropped_total",
    "ebmpc_models_version",
    "ebmpc_replay_transitions",
    "ebmpc_replay_bytes",
    "ebmpc_episodes",
    "ebmpc_agents",
    "ebmpc_agent_queue_depth",
    "ebmpc_replay_fsync_seconds_bucket",
    "ebmpc_retraining_seconds_bucket",
    "ebmpc_training_loss",
    "ebmpc_retraining_share",
    "ebmpc_retraining_slices",
    "ebmpc_retraining_waited_seconds",
    "ebmpc_retraining_starving",
    "ebmpc_dormant_runs",
];

fn scrape(url: &str) -> String {
    ureq::get(url)
        .call()
        .expect("the metrics endpoint answers")
        .body_mut()
        .read_to_string()
        .expect("a text body")
}

/// The value of the sample `name{labels}` (exactly as printed), if present.
fn sample(text: &str, series: &str) -> Option<f64> {
    text.lines()
        .find_map(|line| line.strip_prefix(series)?.strip_prefix(' ')?.parse().ok())
}

#[test]
fn the_metrics_endpoint_serves_every_metric_and_its_counters_move() {
    let dir = TempDir::new("metrics");
    let port = free_port();
    let config = PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(1)
        .toml()
        + &format!("[metrics]\nlisten = \"127.0.0.1:{port}\"\n");
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    let url = format!("http://127.0.0.1:{port}/metrics");
    runtime().block_on(async {
        let spec = RunSpec {
            task: Builtin::Cartpole.name().into(),
            preset: None,
            overrides: Default::default(),
            mode: Default::default(),
            seed: 2,
            task_spec: None,
        };
        let agent = Client::connect(&planner.endpoint, "watched", "a")
            .await
            .unwrap();
        agent.attach(&spec).await.unwrap();
        let before = tokio::task::spawn_blocking({
            let url = url.clone();
            move || scrape(&url)
        })
        .await
        .unwrap();
        assert_eq!(
            sample(&before, "ebmpc_plan_seconds_count{run=\"watched\"}"),
            None
        );
        // The agent is attached and waits for nothing yet.
        assert_eq!(
            sample(
                &before,
                "ebmpc_agent_queue_depth{run=\"watched\",agent=\"a\"}"
            ),
            Some(0.0),
            "{before}"
        );
        let bytes_before = sample(&before, "ebmpc_replay_bytes{run=\"watched\"}").unwrap();
        let fsyncs_before = sample(&before, "ebmpc_replay_fsync_seconds_count{run=\"watched\"}");

        // One explored episode, then planned steps; one refused (out-of-order) step.
        let mut system = ToySystem::new(3);
        let mut action = agent
            .step(&Observation::new(0, 0, system.state.to_vec(), None, None))
            .await
            .unwrap();
        for step in 1..=10 {
            let reward = system.step(&action.action);
            let end = (step == 10).then_some(EpisodeEnd::TimeLimit);
            let obs = Observation::new(0, step, system.state.to_vec(), Some(reward), end);
            if end.is_some() {
                agent.send(&obs).await.unwrap();
            } else {
                action = agent.step(&obs).await.unwrap();
            }
        }
        for step in 0..4 {
            let obs = Observation::new(
                1,
                step,
                system.state.to_vec(),
                (step > 0).then_some(0.0),
                None,
            );
            agent.step(&obs).await.unwrap();
        }
        agent
            .send(&Observation::new(
                1,
                1,
                system.state.to_vec(),
                Some(0.0),
                None,
            ))
            .await
            .unwrap();
        agent.next_error().await.unwrap();

        let after = tokio::task::spawn_blocking(move || scrape(&url))
            .await
            .unwrap();
        for metric in METRICS {
            assert!(after.contains(metric), "{metric} is served:\n{after}");
        }
        let run = |name: &str| format!("{name}{{run=\"watched\"}}");
        assert_eq!(
            sample(&after, &run("ebmpc_plan_seconds_count")),
            Some(4.0),
            "{after}"
        );
        assert_eq!(
            sample(&after, &run("ebmpc_plan_iterations_count")),
            Some(4.0)
        );
        assert_eq!(sample(&after, &run("ebmpc_replay_transitions")), Some(13.0));
        assert_eq!(sample(&after, &run("ebmpc_episodes")), Some(1.0));
        assert!(sample(&after, &run("ebmpc_models_version")).unwrap() >= 1.0);
        // The counters moved while the agent played: the log grew and was synced at the
        // episode's end, and the models it planned with came from a timed retraining.
        let bytes = sample(&after, &run("ebmpc_replay_bytes")).unwrap();
        assert!(bytes > bytes_before, "{bytes} > {bytes_before}");
        let fsyncs = sample(&after, &run("ebmpc_replay_fsync_seconds_count")).unwrap();
        assert!(fsyncs > fsyncs_before.unwrap_or(0.0), "{after}");
        assert!(sample(&after, &run("ebmpc_replay_fsync_seconds_sum")).unwrap() > 0.0);
        let retrainings = sample(&after, &run("ebmpc_retraining_seconds_count")).unwrap();
        assert!(retrainings >= 1.0, "{after}");
        assert!(sample(&after, &run("ebmpc_retraining_seconds_sum")).unwrap() > 0.0);
        let loss = |model: &str| {
            sample(
                &after,
                &format!("ebmpc_training_loss{{run=\"watched\",model=\"{model}\"}}"),
            )
        };
        let (dynamics_loss, energy_loss) = (loss("dynamics").unwrap(), loss("energy").unwrap());
        assert!(dynamics_loss.is_finite() && energy_loss.is_finite());
        assert_eq!(
            sample(
                &after,
                "ebmpc_refused_messages_total{code=\"out_of_order\"}"
            ),
            Some(1.0),
            "{after}"
        );
        // The status report carries the same figures.
        let report = status(&agent.session, PLANNER).await.unwrap();
        assert_eq!(report.refused.get("out_of_order"), Some(&1));
        let watched = &report.runs[0];
        assert_eq!(watched.plan_tally.plans, 4);
        assert_eq!(watched.queue_depth.get("a"), Some(&0), "{watched:?}");
        assert_eq!(watched.replay_bytes as f64, bytes);
        assert_eq!(watched.replay_fsync.count as f64, fsyncs);
        assert_eq!(watched.retraining.count as f64, retrainings);
        let last = watched
            .last_retraining
            .expect("the models came from a retraining");
        assert_eq!(last.dynamics_loss.map(f64::from), Some(dynamics_loss));
        assert_eq!(last.energy_loss.map(f64::from), Some(energy_loss));
        assert_eq!(
            last.models_version as f64,
            sample(&after, &run("ebmpc_models_version")).unwrap()
        );
        assert_eq!(
            sample(&after, &run("ebmpc_plans_cut_total")).unwrap_or(0.0),
            watched.plan_tally.cut as f64
        );
        assert_eq!(
            sample(&after, &run("ebmpc_deadline_misses_total")).unwrap_or(0.0),
            watched.plan_tally.deadline_misses as f64
        );
        assert_eq!(
            sample(&after, &run("ebmpc_plan_step_backs_total")).unwrap_or(0.0),
            watched.plan_tally.stepped_back as f64
        );
        agent.close().await.unwrap();
    });
    planner.stop().unwrap();
}
