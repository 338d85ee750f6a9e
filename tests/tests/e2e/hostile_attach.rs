//! No attach can crash the daemon: every oversized override, an unknown override field, a
//! hostile name and a spec that differs from the run's are refused with an error naming what
//! is wrong, while a well-behaved agent on another run is served throughout; nothing refused
//! reaches the disk, and a restart on the same data dir comes up clean. A run stored with an
//! override over today's limits is set aside (listed as failed) instead of stopping the daemon.
//! A task given in full in the attach is validated field by field (hostile values refused, each
//! naming its field), runs as any other, and is stored with its run so that the restarted
//! daemon resumes it for an agent that names the task only.

use ebmpc_e2e::client::{Client, ToySystem, open_session, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use planner_service::persist::RunDir;
use proto::task::{DeclaredTransforms, ModelTransforms, RewardKind};
use proto::{
    AttachOutcome, AttachRequest, Builtin, Encoding, EpisodeEnd, EpochSchedule, Observation,
    PROTOCOL_VERSION, PlannerOverrides, RunSpec, TaskSpec,
};
use std::time::Duration;

const PLANNER: &str = "hostile";

fn config() -> String {
    PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(1)
        .toml()
}

fn spec(overrides: PlannerOverrides) -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides,
        mode: Default::default(),
        seed: 1,
        task_spec: None,
    }
}

/// A system the planner's catalog does not know, given in full: cartpole's shape, its angle
/// declared, short episodes.
fn custom_task() -> TaskSpec {
    let mut task = Builtin::Cartpole.spec();
    task.name = "my-cartpole".into();
    task.episode_len = 10;
    task.model = ModelTransforms::Declared(DeclaredTransforms {
        angles: vec![1],
        absolute: vec![],
    });
    task
}

fn custom_spec(task_spec: Option<TaskSpec>) -> RunSpec {
    RunSpec {
        task: "my-cartpole".into(),
        task_spec,
        ..spec(PlannerOverrides::default())
    }
}

/// Hostile task specs, with what the refusal must say.
fn hostile_tasks() -> Vec<(RunSpec, &'static str)> {
    let with = |change: &dyn Fn(&mut TaskSpec)| {
        let mut task = custom_task();
        change(&mut task);
        custom_spec(Some(task))
    };
    vec![
        (
            RunSpec {
                task: "walker".into(),
                ..spec(PlannerOverrides::default())
            },
            "unknown task `walker`",
        ),
        (with(&|t| t.obs_dim = 4_000_000_000), "obs_dim = 4000000000"),
        (with(&|t| t.act_dim = 0), "act_dim = 0"),
        (with(&|t| t.episode_len = u32::MAX), "episode_len"),
        (with(&|t| t.action_low = vec![f32::NAN]), "action[0]"),
        (with(&|t| t.action_high = vec![-5.0]), "low < high"),
        (
            with(&|t| t.action_low = vec![0.0; 1000]),
            "action_low has 1000 numbers",
        ),
        (with(&|t| t.control_dt = f64::INFINITY), "control_dt"),
        (with(&|t| t.magnitudes.observation = 3e38), "magnitudes"),
        (
            with(&|t| t.reward = RewardKind::Builtin(Builtin::Ant)),
            "builtin reward `ant` needs obs_dim = 27",
        ),
        (
            with(&|t| t.reward = RewardKind::Expression("-s_next[9]^2".into())),
            "index 9 out of range for s_next",
        ),
        (with(&|t| t.name = "other".into()), "must agree"),
        (
            RunSpec {
                task: "a/b".into(),
                ..with(&|t| t.name = "a/b".into())
            },
            "task name: invalid name",
        ),
        (
            RunSpec {
                task: "cartpole".into(),
                task_spec: Some(Builtin::Cartpole.spec()).map(|mut t| {
                    t.episode_len = 5;
                    t
                }),
                ..spec(PlannerOverrides::default())
            },
            "in this planner's catalog with another spec",
        ),
    ]
}

/// Every client-chosen size, oversized, with the field the refusal must name.
fn oversized() -> Vec<(PlannerOverrides, &'static str)> {
    let o = PlannerOverrides::default;
    vec![
        (
            PlannerOverrides {
                dynamics_hidden_size: Some(4_000_000_000),
                ..o()
            },
            "dynamics_hidden_size = 4000000000",
        ),
        (
            PlannerOverrides {
                energy_hidden_size: Some(u32::MAX),
                ..o()
            },
            "energy_hidden_size",
        ),
        (
            PlannerOverrides {
                dynamics_hidden_layers: Some(u32::MAX),
                ..o()
            },
            "dynamics_hidden_layers",
        ),
        (
            PlannerOverrides {
                energy_hidden_layers: Some(1_000_000),
                ..o()
            },
            "energy_hidden_layers",
        ),
        (
            PlannerOverrides {
                ensemble_size: Some(u32::MAX),
                ..o()
            },
            "ensemble_size",
        ),
        (
            PlannerOverrides {
                particles: Some(u32::MAX),
                ..o()
            },
            "particles",
        ),
        (
            PlannerOverrides {
                horizon: Some(u32::MAX),
                ..o()
            },
            "horizon",
        ),
        (
            PlannerOverrides {
                population: Some(u32::MAX),
                elites: Some(10),
                ..o()
            },
            "population",
        ),
        (
            PlannerOverrides {
                cem_iterations: Some(u32::MAX),
                ..o()
            },
            "cem_iterations",
        ),
        (
            PlannerOverrides {
                exploration_episodes: Some(u32::MAX),
                ..o()
            },
            "exploration_episodes",
        ),
        (
            PlannerOverrides {
                dynamics_epochs: Some(u32::MAX),
                ..o()
            },
            "dynamics_epochs",
        ),
        (
            PlannerOverrides {
                energy_epochs: Some(u32::MAX),
                ..o()
            },
            "energy_epochs",
        ),
        (
            PlannerOverrides {
                dynamics_batch_size: Some(u32::MAX),
                ..o()
            },
            "dynamics_batch_size",
        ),
        (
            PlannerOverrides {
                energy_batch_size: Some(u32::MAX),
                ..o()
            },
            "energy_batch_size",
        ),
        (
            PlannerOverrides {
                epoch_schedule: Some(EpochSchedule::DropAfter {
                    after_episodes: 0,
                    epochs: u32::MAX,
                }),
                ..o()
            },
            "epoch_schedule.drop_after.epochs",
        ),
        (
            PlannerOverrides {
                energy_weight: Some(f32::MAX),
                ..o()
            },
            "energy_weight",
        ),
        (
            PlannerOverrides {
                energy_noise_sigma: Some(f32::MAX),
                ..o()
            },
            "energy_noise_sigma",
        ),
        (
            PlannerOverrides {
                dynamics_learning_rate: Some(f32::MAX),
                ..o()
            },
            "dynamics_learning_rate",
        ),
        (
            PlannerOverrides {
                cem_smoothing: Some(f32::MAX),
                ..o()
            },
            "cem_smoothing",
        ),
        (
            PlannerOverrides {
                deadline_ms: Some(u32::MAX),
                ..o()
            },
            "deadline_ms = 4294967295",
        ),
        (
            PlannerOverrides {
                deadline_ms: Some(1),
                ..o()
            },
            "deadline_ms must be 0 (off) or at least",
        ),
        (
            PlannerOverrides {
                max_gradient_steps: Some(0),
                ..o()
            },
            "max_gradient_steps",
        ),
        // Each size within its limit, together over the plan budget.
        (
            PlannerOverrides {
                population: Some(5000),
                elites: Some(10),
                particles: Some(100),
                horizon: Some(200),
                cem_iterations: Some(50),
                dynamics_hidden_size: Some(2048),
                ..o()
            },
            "plan_multiply_adds",
        ),
    ]
}

/// A well-behaved agent: `episodes` episodes of `steps` steps on the toy system, every step
/// answered with an action.
async fn play(client: &Client, episodes: u32, steps: u32) {
    let mut system = ToySystem::new(3);
    for episode in 0..episodes {
        let first = Observation::new(episode, 0, system.state.to_vec(), None, None);
        let mut action = client.step(&first).await.expect("step 0 answered");
        for step in 1..=steps {
            let reward = system.step(&action.action);
            let end = (step == steps).then_some(EpisodeEnd::TimeLimit);
            let msg = Observation::new(episode, step, system.state.to_vec(), Some(reward), end);
            if end.is_some() {
                client.send(&msg).await.unwrap();
            } else {
                action = client.step(&msg).await.expect("every step answered");
                assert!(action.action.iter().all(|a| a.is_finite()));
            }
        }
    }
}

/// The refusal of an attach with raw `payload`, as text.
async fn refusal(client: &Client, run: &str, payload: Vec<u8>, mime: &str) -> String {
    let reply = client.attach_raw(run, payload, mime).await.unwrap();
    match reply.outcome {
        AttachOutcome::Rejected(report) => report.message,
        AttachOutcome::Accepted(a) => panic!("attach to {run} accepted: {a:?}"),
    }
}

async fn hostile_attaches(endpoint: &str) {
    let hostile = Client::connect(endpoint, "hostile", "h").await.unwrap();
    for (i, (overrides, field)) in oversized().into_iter().enumerate() {
        let run = format!("hostile-{i}");
        let request = AttachRequest {
            version: PROTOCOL_VERSION,
            agent: "h".into(),
            spec: spec(overrides.clone()),
            session: None,
        };
        let bytes = proto::encode(&request, Encoding::Postcard).unwrap();
        let message = refusal(&hostile, &run, bytes, Encoding::Postcard.mime()).await;
        assert!(message.contains(field), "{overrides:?}: {message}");
        if !field.starts_with("plan_") && !message.contains("must") {
            assert!(message.contains("limit"), "{overrides:?}: {message}");
        }
    }
    for (i, (asked, expected)) in hostile_tasks().into_iter().enumerate() {
        let run = format!("hostile-task-{i}");
        let request = AttachRequest {
            version: PROTOCOL_VERSION,
            agent: "h".into(),
            spec: asked,
            session: None,
        };
        let bytes = proto::encode(&request, Encoding::Postcard).unwrap();
        let message = refusal(&hostile, &run, bytes, Encoding::Postcard.mime()).await;
        assert!(message.contains(expected), "{expected}: {message}");
    }
    let json = format!(
        r#"{{"version":{PROTOCOL_VERSION},"agent":"h","spec":{{"task":"j","task_spec":{{"name":"j","obs_dim":2,"act_dim":1,"action_low":[-1],"action_high":[1],"episode_len":10,"control_dt":0.1,"reward":"learned","gravity":9.8}}}}}}"#
    );
    let message = refusal(&hostile, "json-task", json.into_bytes(), "application/json").await;
    assert!(message.contains("unknown field `gravity`"), "{message}");
    // The issue's own reproduction, in JSON, and a mistyped field.
    let json = format!(
        r#"{{"version":{PROTOCOL_VERSION},"agent":"h","spec":{{"task":"cartpole","overrides":{{"dynamics_hidden_size":4000000000}}}}}}"#
    );
    let message = refusal(&hostile, "json-huge", json.into_bytes(), "application/json").await;
    assert!(
        message.contains("dynamics_hidden_size = 4000000000 is over this planner's limit of 2048"),
        "{message}"
    );
    let json = format!(
        r#"{{"version":{PROTOCOL_VERSION},"agent":"h","spec":{{"task":"cartpole","overrides":{{"populaton":50}}}}}}"#
    );
    let message = refusal(&hostile, "json-typo", json.into_bytes(), "application/json").await;
    assert!(message.contains("unknown field `populaton`"), "{message}");
    // A name of 10,000 characters is refused without being echoed whole.
    let long = "n".repeat(10_000);
    let request = AttachRequest {
        version: PROTOCOL_VERSION,
        agent: long.clone(),
        spec: spec(PlannerOverrides::default()),
        session: None,
    };
    let bytes = proto::encode(&request, Encoding::Postcard).unwrap();
    let message = refusal(&hostile, "named", bytes, Encoding::Postcard.mime()).await;
    assert!(
        message.contains("invalid name") && message.len() < 300,
        "{message}"
    );
    // A second agent asking the good run for another seed or other overrides is refused.
    let mut other = spec(PlannerOverrides::default());
    other.seed = 99;
    let request = AttachRequest {
        version: PROTOCOL_VERSION,
        agent: "intruder".into(),
        spec: other,
        session: None,
    };
    let bytes = proto::encode(&request, Encoding::Postcard).unwrap();
    let message = refusal(&hostile, "good", bytes, Encoding::Postcard.mime()).await;
    assert!(message.contains("seed 1, not 99"), "{message}");
    let request = AttachRequest {
        version: PROTOCOL_VERSION,
        agent: "intruder".into(),
        spec: spec(PlannerOverrides {
            population: Some(30),
            ..Default::default()
        }),
        session: None,
    };
    let bytes = proto::encode(&request, Encoding::Postcard).unwrap();
    let message = refusal(&hostile, "good", bytes, Encoding::Postcard.mime()).await;
    assert!(message.contains("overrides"), "{message}");
    hostile.close().await.unwrap();
}

#[test]
fn hostile_attaches_are_refused_and_the_daemon_keeps_serving() {
    let dir = TempDir::new("hostile-attach");
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let endpoint = planner.endpoint.clone();
    let rt = runtime();
    rt.block_on(async {
        let good = Client::connect(&endpoint, "good", "g").await.unwrap();
        good.attach(&spec(PlannerOverrides::default()))
            .await
            .unwrap();
        // The good agent plays (through a retraining) while the hostile attaches arrive.
        tokio::join!(play(&good, 2, 30), hostile_attaches(&endpoint));
        good.close().await.unwrap();
        // A task given in full runs like a catalog task.
        let custom = Client::connect(&endpoint, "custom", "c").await.unwrap();
        let accepted = custom
            .attach(&custom_spec(Some(custom_task())))
            .await
            .unwrap();
        assert_eq!(accepted.task, "my-cartpole");
        play(&custom, 1, 10).await;
        custom.close().await.unwrap();
    });
    planner.stop().unwrap();
    let runs = std::fs::read_dir(planner.data_dir.join("runs"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect::<Vec<_>>();
    let mut runs = runs;
    runs.sort();
    assert_eq!(runs, ["custom", "good"], "no refused run reached the disk");
    let custom_task = proto::Task::intern(custom_task(), &Default::default()).unwrap();
    let path = planner.data_dir.join("runs/custom");
    let replay = planner_service::replay::ReplayBuffer::read(&path, custom_task).unwrap();
    assert_eq!(replay.len(), 10);
    assert_eq!(planner.replay("good", Builtin::Cartpole).unwrap().len(), 60);

    // A run stored by an older daemon with a size over today's limits: set aside, not fatal.
    let poisoned = RunDir::new(&planner.data_dir, "poisoned");
    poisoned
        .write_spec(&spec(PlannerOverrides {
            dynamics_hidden_size: Some(4_000_000_000),
            ..Default::default()
        }))
        .unwrap();

    let mut planner =
        Planner::start(dir.path(), &config()).expect("the planner restarts on the same data");
    rt.block_on(async {
        let session = open_session(&planner.endpoint).await.unwrap();
        let report = status(&session, PLANNER).await.unwrap();
        let names: Vec<&str> = report.runs.iter().map(|r| r.name.as_str()).collect();
        assert_eq!(names, ["custom", "good"]);
        assert_eq!(report.runs[1].episodes, 2);
        assert_eq!(report.failed_runs.len(), 1, "{:?}", report.failed_runs);
        assert_eq!(report.failed_runs[0].name, "poisoned");
        assert!(
            report.failed_runs[0]
                .reason
                .contains("dynamics_hidden_size"),
            "{:?}",
            report.failed_runs[0]
        );
        let again = Client::connect(&planner.endpoint, "poisoned", "p")
            .await
            .unwrap();
        let err = again
            .attach(&spec(PlannerOverrides::default()))
            .await
            .unwrap_err();
        assert!(err.to_string().contains("cannot be opened"), "{err}");
        let good = Client::connect(&planner.endpoint, "good", "g")
            .await
            .unwrap();
        let accepted = good
            .attach(&spec(PlannerOverrides::default()))
            .await
            .unwrap();
        assert_eq!(accepted.next_episode, 2);
        let first = Observation::new(2, 0, vec![0.0; 4], None, None);
        let action = good.step(&first).await.unwrap();
        assert_eq!(action.action.len(), 1);
        tokio::time::timeout(Duration::from_secs(30), good.close())
            .await
            .unwrap()
            .unwrap();
        again.close().await.unwrap();
        // The restarted daemon rebuilt the custom task from the run's stored spec: an agent
        // naming the task only joins it.
        let custom = Client::connect(&planner.endpoint, "custom", "c")
            .await
            .unwrap();
        let accepted = custom.attach(&custom_spec(None)).await.unwrap();
        assert_eq!(
            (accepted.task.as_str(), accepted.next_episode),
            ("my-cartpole", 1)
        );
        assert_eq!(accepted.episodes_done, 1);
        custom.close().await.unwrap();
        session.close().await.unwrap();
    });
    planner.stop().unwrap();
}
