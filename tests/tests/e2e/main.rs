//! The end-to-end tests: the real `planner-service` and `sim-bridge` binaries (and the Python
//! package, etcd, a Zenoh router) driven as processes, one module per capability.
//!
//! They are one test executable, not one per file: one crate to type-check and link, and
//! libtest runs its tests side by side (`--test-threads`, the machine's cores by default), so
//! that a test waiting on a lease's expiry or a process's exit leaves the cores to another test
//! instead of holding the whole suite. Run one module with
//! `cargo test -p ebmpc-e2e --test e2e fleet_etcd::`, one test with its full path and `--exact`.

mod agent_identity;
mod all_tasks;
mod bad_input;
mod cartpole;
mod deadline;
mod declared_task;
mod deploy;
mod dormant_runs;
mod durability;
mod fair_share;
mod fleet;
mod fleet_etcd;
mod fleet_ownership;
mod forged_tokens;
mod gym_driver;
mod hostile_attach;
mod hostile_payload;
mod idle_agent;
mod kill_loop;
mod learned_reward;
mod metrics;
mod poison;
mod protocol_edges;
mod python_example;
mod python_package;
mod replay_budget;
mod retraining_share;
mod shutdown;
mod slow_disk;
mod wildcard_keys;
