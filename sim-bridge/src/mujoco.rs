//! A MuJoCo model and its data, checked against proto's task catalog.
//!
//! Every task owns one [`MjSim`]: the task module says how to map the physics state to its
//! observation and how to sample an initial state; this module does what is common to all of
//! them: loading the embedded MJCF, checking that it agrees with the catalog (a model that
//! silently ran at another control rate or with other action bounds would make the planner's
//! learned model and the real system disagree), applying controls and advancing one control step.

use crate::error::SimError;
use mujoco_rs::prelude::{
    MjData, MjLogMessage, MjModel, MjtIntegrator, MjtLogLevel, MjtWarning, set_log_handler,
};
use proto::Task;
use std::sync::Once;

/// How a task's MJCF is meant to be run.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ModelConfig {
    /// The MJCF text (embedded with `include_str!`, so the binary is self-contained).
    pub xml: &'static str,
    /// Physics steps per control step.
    pub substeps: u32,
    /// The integrator the task is specified with (tasks.md).
    pub integrator: MjtIntegrator,
}

/// MuJoCo had to reset a simulation whose state blew up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Unstable;

/// One loaded model and its simulation state.
#[derive(Debug)]
pub(crate) struct MjSim {
    data: MjData<Box<MjModel>>,
    substeps: u32,
    /// The MJCF the model was loaded from (a renderer loads its own copy).
    #[cfg(feature = "render")]
    xml: &'static str,
}

impl MjSim {
    /// Loads `config.xml` and checks it against `spec`: actuator count, control ranges equal to
    /// the action bounds, `timestep × substeps = control_dt`, and the integrator.
    pub fn load(spec: &Task, config: ModelConfig) -> Result<Self, SimError> {
        route_mujoco_messages();
        let task = spec
            .builtin()
            .expect("sim-bridge's simulators load their own catalog entry");
        let model = MjModel::from_xml_string(config.xml)
            .map_err(|source| SimError::ModelLoad { task, source })?;
        let mismatch = |detail: String| SimError::ModelMismatch { task, detail };

        let nu = model.ffi().nu as usize;
        if nu != spec.act_dim {
            return Err(mismatch(format!(
                "{nu} actuators for {} action dimensions",
                spec.act_dim
            )));
        }
        for (i, range) in model.actuator_ctrlrange().iter().enumerate() {
            let (lo, hi) = (spec.action_low[i] as f64, spec.action_high[i] as f64);
            if range[0] != lo || range[1] != hi {
                return Err(mismatch(format!(
                    "actuator {i} ctrlrange [{}, {}] but action bounds [{lo}, {hi}]",
                    range[0], range[1]
                )));
            }
        }
        let opt = model.opt();
        let dt = opt.timestep * f64::from(config.substeps);
        if (dt - spec.control_dt).abs() > 1e-9 {
            return Err(mismatch(format!(
                "timestep {} × {} substeps = {dt} s, catalog control dt {} s",
                opt.timestep, config.substeps, spec.control_dt
            )));
        }
        if opt.integrator != config.integrator as i32 {
            return Err(mismatch(format!(
                "integrator {} but the task is specified with {:?}",
                opt.integrator, config.integrator
            )));
        }

        let data = MjData::new(Box::new(model));
        Ok(Self {
            data,
            substeps: config.substeps,
            #[cfg(feature = "render")]
            xml: config.xml,
        })
    }

    /// The MJCF text the model was loaded from.
    #[cfg(feature = "render")]
    pub fn xml(&self) -> &'static str {
        self.xml
    }

    /// Generalised positions.
    pub fn qpos(&self) -> &[f64] {
        self.data.qpos()
    }

    /// Generalised velocities.
    pub fn qvel(&self) -> &[f64] {
        self.data.qvel()
    }

    /// Puts the simulation in the state `(qpos, qvel)` at time 0 with zero controls, and
    /// recomputes the derived quantities (positions of bodies and sites) for it.
    ///
    /// # Panics
    /// If the slices do not have the model's `nq` and `nv` lengths (a bug in the task module).
    pub fn set_state(&mut self, qpos: &[f64], qvel: &[f64]) {
        self.data.reset();
        self.data.qpos_mut().copy_from_slice(qpos);
        self.data.qvel_mut().copy_from_slice(qvel);
        self.data.forward();
    }

    /// Holds `ctrl` (already clamped and finite) for one control step of `substeps` physics steps.
    ///
    /// # Errors
    /// [`Unstable`] if MuJoCo found a position, velocity or acceleration non-finite or beyond
    /// its limits. MuJoCo then silently resets the state to the model's rest pose, which must
    /// not be passed off as the system's next state.
    pub fn advance(&mut self, ctrl: &[f32]) -> Result<(), Unstable> {
        for (c, &a) in self.data.ctrl_mut().iter_mut().zip(ctrl) {
            *c = f64::from(a);
        }
        let before = self.instabilities();
        for _ in 0..self.substeps {
            self.data.step();
        }
        if self.instabilities() == before {
            Ok(())
        } else {
            Err(Unstable)
        }
    }

    /// How often MuJoCo has reset the simulation for a bad state since the last reset.
    fn instabilities(&self) -> i64 {
        let warnings = self.data.warning();
        [
            MjtWarning::mjWARN_BADQPOS,
            MjtWarning::mjWARN_BADQVEL,
            MjtWarning::mjWARN_BADQACC,
        ]
        .iter()
        .map(|&w| i64::from(warnings[w as usize].number))
        .sum()
    }

    /// Recomputes the positions of bodies and sites for the current state. A physics step
    /// computes them *before* integrating, so after [`MjSim::advance`] they describe the state
    /// one substep back; tasks that observe positions call this first.
    pub fn update_kinematics(&mut self) {
        self.data.kinematics();
    }

    /// Index of the named site, for [`MjSim::site_xpos`].
    pub fn site_id(&self, name: &str) -> Option<usize> {
        self.data
            .model()
            .name_to_id(mujoco_rs::prelude::MjtObjBase::mjOBJ_SITE, name)
    }

    /// Cartesian position of site `id` as of the last kinematics pass ([`MjSim::set_state`]
    /// or [`MjSim::update_kinematics`]).
    pub fn site_xpos(&self, id: usize) -> [f64; 3] {
        self.data.site_xpos()[id]
    }

    /// Mass of every body (the world first), as MuJoCo computed it from the geoms.
    #[cfg(test)]
    pub fn body_masses(&self) -> Vec<f64> {
        self.data.model().body_mass().to_vec()
    }

    /// Cartesian position of the named site (valid after [`MjSim::set_state`] or a step).
    #[cfg(test)]
    pub fn site_position(&self, name: &str) -> Option<[f64; 3]> {
        Some(self.site_xpos(self.site_id(name)?))
    }
}

/// Sends MuJoCo's messages (warnings of unstable simulations, mostly) to `tracing` under the
/// target `mujoco`, instead of MuJoCo's default: stdout plus a `MUJOCO_LOG.TXT` file in whatever
/// the working directory is.
///
/// Runs once, before this crate's first use of MuJoCo: every use goes through
/// [`MjSim::load`], which calls this first, and `Once` holds any other caller until the handler
/// is in place.
fn route_mujoco_messages() {
    static ROUTED: Once = Once::new();
    ROUTED.call_once(|| {
        // SAFETY: no thread uses MuJoCo while this runs: sim-bridge is the process's only
        // MuJoCo user, and each of its uses starts with `MjSim::load`, which blocks on this
        // `Once` until the handler is installed.
        unsafe { set_log_handler(to_tracing) }
    });
}

/// A MuJoCo message as a `tracing` event. (An error-level message ends the process after this
/// returns: MuJoCo cannot continue after one.)
fn to_tracing(message: &MjLogMessage) {
    let subject = message.subject();
    let body = message.body().unwrap_or_default();
    match message.level() {
        MjtLogLevel::mjLOG_DEBUG => tracing::debug!(target: "mujoco", "{subject} {body}"),
        MjtLogLevel::mjLOG_INFO => tracing::info!(target: "mujoco", "{subject} {body}"),
        MjtLogLevel::mjLOG_WARNING => tracing::warn!(target: "mujoco", "{subject} {body}"),
        MjtLogLevel::mjLOG_ERROR => tracing::error!(target: "mujoco", "{subject} {body}"),
    }
}
