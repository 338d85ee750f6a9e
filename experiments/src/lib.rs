//! Reproducing the paper's comparisons with one command each.
//!
//! - [`launcher`]: `experiment` runs a task with several methods and seeds through the real
//!   deployment path (a `planner-service` daemon and one `sim-bridge` process per run, over
//!   Zenoh on loopback), resumable, with progress, into `results/<task>/<stamp>/`; [`queue`]
//!   orders its runs within a wall-clock budget, [`resume_state`] packs what an unfinished run
//!   needs to continue elsewhere, and [`provenance`] records where each finished run ran.
//! - [`plot`]: learning curves from an experiment's `episodes.csv` (the paper's Figure 4).
//! - [`figures`]: the paper's Figure 3 (DEEN vs DAE on a 1-D mixture) and Figure 5
//!   (imagination against reality), computed in-process with the planner's library and the
//!   simulator's [`sim_bridge::Env`].
//! - [`run_ledger`]: every run of a folder, one row each: its planned episodes' returns, and
//!   where it ran (CPUs, kernels, binaries, dates), from the run files and records.
//! - [`compare`]: whether one method beats another at an episode, per method and seed-paired,
//!   with Student-t intervals over seeds.
//! - [`distance`]: how far a locomotion task's body travelled per episode, from the stored
//!   replay logs (does the ant walk, or only stay up?).
//! - [`replan`]: optimisers side by side on one stored run's frozen models, in the simulator:
//!   real return and milliseconds per plan.
//! - [`model_error`]: how wrong a stored run's models are on its own stored transitions, per
//!   episode and region of the state space, and how familiar the regulariser found them
//!   (both load the run through [`stored_run`]).
//!
//! This crate exists so that planner-service never depends on sim-bridge: Figure 5 needs both
//! the planner (to optimise a plan) and the simulator (to execute it), and the launcher and the
//! plotting (plotters, indicatif) have no business in the daemon's dependency tree.

pub mod compare;
pub mod distance;
pub mod figures;
pub mod launcher;
pub mod manifest;
pub mod method;
pub mod model_error;
pub mod plot;
pub mod progress;
pub mod provenance;
pub mod queue;
pub mod replan;
pub mod results;
pub mod resume_state;
pub mod run_ledger;
pub mod scale;
pub mod stored_run;
