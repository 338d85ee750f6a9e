//! One run's slow disk never delays another run's actions: while a write to run `slow`'s replay
//! log is held inside the write (as a stuck device holds it), run `fast` is attached, stepped
//! and answered as usual; once the write is released, `slow`'s held step is answered, its agent
//! carries on, and everything both agents sent is in their logs.
//!
//! The daemon runs in this process (the real service over Zenoh, on a free loopback endpoint)
//! so that one run's log can be given a disk the test holds ([`LogDisk`]). Its runtime has one
//! worker thread: a run's disk I/O done on a worker (rather than on the blocking pool) would
//! then stall every run, whatever else the daemon does, so the test cannot pass by luck of
//! scheduling.

use ebmpc_e2e::client::{ANSWER_TIMEOUT, Answer, Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{TempDir, free_endpoint};
use planner_service::config::ServiceConfig;
use planner_service::replay::{LogFile, ReplayBuffer};
use planner_service::run::LogDisk;
use planner_service::service::Service;
use proto::{Builtin, EpisodeEnd, Observation, RunSpec};
use std::fs::File;
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::Duration;

const PLANNER: &str = "slow-disk";
/// The run whose disk is held.
const SLOW: &str = "slow";
/// The run that must be served meanwhile.
const FAST: &str = "fast";
/// Steps of `slow`'s episode; its write is held at [`HELD_STEP`].
const SLOW_STEPS: u32 = 6;
const HELD_STEP: u32 = 3;
/// Steps `fast` plays, every one answered, while `slow`'s write is held.
const FAST_STEPS: u32 = 8;

/// A disk the test holds: while held, every write waits inside the write until released.
#[derive(Debug, Default)]
struct Hold {
    state: Mutex<HoldState>,
    changed: Condvar,
}

#[derive(Debug, Default)]
struct HoldState {
    held: bool,
    /// Writes waiting on the hold now.
    waiting: usize,
}

impl Hold {
    fn lock(&self) -> std::sync::MutexGuard<'_, HoldState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn set(&self, held: bool) {
        self.lock().held = held;
        self.changed.notify_all();
    }

    /// Called by every write: waits while the disk is held.
    fn pass(&self) {
        let mut state = self.lock();
        state.waiting += 1;
        self.changed.notify_all();
        while state.held {
            state = self
                .changed
                .wait(state)
                .unwrap_or_else(PoisonError::into_inner);
        }
        state.waiting -= 1;
    }

    /// Writes waiting on the hold once one is (or after `patience`, however many are).
    fn wait_for_a_held_write(&self, patience: Duration) -> usize {
        let state = self.lock();
        let (state, _) = self
            .changed
            .wait_timeout_while(state, patience, |s| s.waiting == 0)
            .unwrap_or_else(PoisonError::into_inner);
        state.waiting
    }
}

/// Releases the hold when dropped, also when the test fails: a write held for good would keep
/// the daemon's runtime from shutting down.
struct ReleaseOnDrop(Arc<Hold>);

impl Drop for ReleaseOnDrop {
    fn drop(&mut self) {
        self.0.set(false);
    }
}

/// `slow`'s log file: every write passes the hold first.
#[derive(Debug)]
struct HeldFile {
    file: File,
    hold: Arc<Hold>,
}

impl LogFile for HeldFile {
    fn append_bytes(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.hold.pass();
        self.file.append_bytes(bytes)
    }

    fn truncate_to(&mut self, len: u64) -> std::io::Result<()> {
        self.file.truncate_to(len)
    }

    fn sync_data(&mut self) -> std::io::Result<()> {
        self.file.sync_data()
    }
}

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides: Default::default(),
        mode: Default::default(),
        seed: 3,
        task_spec: None,
    }
}

fn config(dir: &TempDir, endpoint: &str) -> ServiceConfig {
    let path = dir.path().join("planner.toml");
    // Random actions throughout: the test is about storage, not planning.
    let text = PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(10)
        .toml();
    std::fs::write(&path, text).unwrap();
    let mut config = ServiceConfig::load(&path).unwrap();
    config.listen = vec![endpoint.to_string()];
    config.data_dir = dir.path().join("data");
    config
}

/// An agent's place in its episode: the system it controls and the last action it received.
struct Agent {
    system: ToySystem,
    action: Option<Vec<f32>>,
    /// The state of every observation sent, in order.
    sent: Vec<f32>,
}

impl Agent {
    fn new(seed: u32) -> Self {
        Self {
            system: ToySystem::new(seed),
            action: None,
            sent: Vec::new(),
        }
    }

    /// Applies the last action received and builds the observation of `step` of episode 0
    /// (the episode's last if `last`).
    fn observe(&mut self, step: u32, last: bool) -> Observation {
        let reward = self.action.as_ref().map(|a| self.system.step(a));
        let end = last.then_some(EpisodeEnd::TimeLimit);
        let msg = Observation::new(0, step, self.system.state.to_vec(), reward, end);
        self.sent.push(msg.obs[0]);
        msg
    }

    /// Plays steps `from..=to` of episode 0, which ends at `last`: every step before it is
    /// answered with an action.
    async fn play(&mut self, client: &Client, from: u32, to: u32, last: u32) {
        for step in from..=to {
            let msg = self.observe(step, step == last);
            if step == last {
                client.send(&msg).await.unwrap();
            } else {
                let answer = client.step(&msg).await;
                self.action = Some(
                    answer
                        .unwrap_or_else(|e| panic!("{}: {e}", client.run))
                        .action,
                );
            }
        }
    }
}

#[test]
fn a_run_whose_disk_is_held_never_delays_another_runs_actions() {
    let dir = TempDir::new("slow-disk");
    let endpoint = free_endpoint();
    let hold = Arc::new(Hold::default());
    let service_runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let _release = ReleaseOnDrop(hold.clone());
    let disk = {
        let hold = hold.clone();
        LogDisk::wrapped(move |run, file| -> Box<dyn LogFile> {
            if run == SLOW {
                Box::new(HeldFile {
                    file,
                    hold: hold.clone(),
                })
            } else {
                Box::new(file)
            }
        })
    };
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let served = service_runtime.spawn(Service::serve_with(
        config(&dir, &endpoint),
        async move {
            let _ = stopped.await;
        },
        disk,
    ));

    let (slow_states, fast_states) = runtime().block_on(async {
        let slow = Client::connect(&endpoint, SLOW, "a").await.unwrap();
        slow.attach(&spec()).await.unwrap();
        let fast = Client::connect(&endpoint, FAST, "b").await.unwrap();
        fast.attach(&spec()).await.unwrap();

        let mut slow_agent = Agent::new(1);
        slow_agent.play(&slow, 0, HELD_STEP - 1, SLOW_STEPS).await;
        // The disk of `slow` stops: the write of its next step is held inside the write.
        hold.set(true);
        slow.send(&slow_agent.observe(HELD_STEP, false))
            .await
            .unwrap();
        let waiting = {
            let hold = hold.clone();
            tokio::task::spawn_blocking(move || hold.wait_for_a_held_write(ANSWER_TIMEOUT))
                .await
                .unwrap()
        };
        assert_eq!(waiting, 1, "the held step's write reached the disk");

        // Meanwhile `fast` plays a whole episode, every step answered.
        let mut fast_agent = Agent::new(2);
        fast_agent.play(&fast, 0, FAST_STEPS, FAST_STEPS).await;
        assert_eq!(hold.lock().waiting, 1, "slow's write was held all along");
        let pending = slow.take_pending().unwrap();
        assert!(pending.is_empty(), "a held step was answered: {pending:?}");

        // The disk comes back: the held step is answered, and `slow` finishes its episode.
        hold.set(false);
        match slow.answer(ANSWER_TIMEOUT).await.unwrap() {
            Answer::Action(action) => {
                assert_eq!((action.episode, action.step), (0, HELD_STEP));
                slow_agent.action = Some(action.action);
            }
            Answer::Error(report) => panic!("the held step was refused: {report}"),
        }
        slow_agent
            .play(&slow, HELD_STEP + 1, SLOW_STEPS, SLOW_STEPS)
            .await;

        // Both episodes are stored before the daemon stops.
        for _ in 0..600 {
            let report = status(&slow.session, PLANNER).await.unwrap();
            if report.runs.iter().all(|run| run.episodes == 1) && report.runs.len() == 2 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        slow.close().await.unwrap();
        fast.close().await.unwrap();
        (slow_agent.sent, fast_agent.sent)
    });
    stop.send(()).unwrap();
    service_runtime.block_on(served).unwrap().unwrap();

    // Everything each agent sent is in its run's log: one transition per answered step and
    // the episode's last, each `next_obs` the state sent, and the episode finished.
    for (run, states) in [(SLOW, slow_states), (FAST, fast_states)] {
        let path = dir.path().join("data/runs").join(run);
        let buffer = ReplayBuffer::read(&path, Builtin::Cartpole.task()).unwrap();
        let stored: Vec<f32> = (0..buffer.len())
            .map(|i| buffer.transitions().row(i).2[0])
            .collect();
        assert_eq!(stored, states[1..], "{run}: the stored next states");
        assert_eq!(buffer.episodes().len(), 1, "{run}");
        assert_eq!(buffer.episodes()[0].end, EpisodeEnd::TimeLimit, "{run}");
    }
}
