//! Validation of received messages against the task they claim to belong to.
//!
//! Nothing reaches a replay buffer or a planner without passing through here: a wrong
//! dimension or a non-finite number is rejected with an error the sender can act on.

use crate::messages::{Action, ErrorCode, ErrorReport, Observation};
use crate::task::{Magnitudes, TaskSpec};

/// Why a message was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ValidationError {
    #[error("{what} has {found} numbers, task {task} needs {expected}")]
    Dimension {
        what: &'static str,
        task: String,
        expected: usize,
        found: usize,
    },
    #[error("{what}[{index}] is {value}, only finite numbers are accepted")]
    NonFinite {
        what: &'static str,
        index: usize,
        value: f32,
    },
    #[error("reward is {0}, only finite numbers are accepted")]
    NonFiniteReward(f32),
    #[error("{what}[{index}] is {value:e}, beyond this task's bound of ±{bound:e}")]
    OutOfRange {
        what: &'static str,
        index: usize,
        value: f32,
        bound: f32,
    },
    #[error(
        "observation[{index}] is {value}, outside the task's observation bounds [{low}, {high}]"
    )]
    ObservationOutOfBounds {
        index: usize,
        value: f32,
        low: f32,
        high: f32,
    },
    #[error("step 0 starts an episode and carries no reward")]
    RewardAtReset,
    #[error("step {0} carries no reward")]
    MissingReward(u32),
    #[error("step 0 starts an episode: no action was applied before it")]
    AppliedAtReset,
    #[error("applied action[{index}] is {value}, outside the task's bounds [{low}, {high}]")]
    AppliedOutOfRange {
        index: usize,
        value: f32,
        low: f32,
        high: f32,
    },
}

impl ValidationError {
    /// The error code reported to the sender.
    pub fn code(&self) -> ErrorCode {
        match self {
            ValidationError::Dimension { .. } => ErrorCode::Dimension,
            ValidationError::NonFinite { .. } | ValidationError::NonFiniteReward(_) => {
                ErrorCode::NonFinite
            }
            ValidationError::OutOfRange { .. }
            | ValidationError::AppliedOutOfRange { .. }
            | ValidationError::ObservationOutOfBounds { .. } => ErrorCode::OutOfRange,
            ValidationError::RewardAtReset
            | ValidationError::MissingReward(_)
            | ValidationError::AppliedAtReset => ErrorCode::OutOfOrder,
        }
    }

    /// The report sent back to the sender.
    pub fn report(&self, episode: u32, step: u32) -> ErrorReport {
        ErrorReport::new(self.code(), self.to_string()).at(episode, step)
    }
}

/// Checks that `values` has `expected` finite numbers.
pub fn check_vector(
    what: &'static str,
    task: &TaskSpec,
    values: &[f32],
    expected: usize,
) -> Result<(), ValidationError> {
    if values.len() != expected {
        return Err(ValidationError::Dimension {
            what,
            task: task.name.clone(),
            expected,
            found: values.len(),
        });
    }
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(ValidationError::NonFinite {
            what,
            index,
            value: values[index],
        }),
        None => Ok(()),
    }
}

/// Checks that every value of `values` is within `±bound`.
fn check_magnitude(what: &'static str, values: &[f32], bound: f32) -> Result<(), ValidationError> {
    match values.iter().position(|v| v.abs() > bound) {
        Some(index) => Err(ValidationError::OutOfRange {
            what,
            index,
            value: values[index],
            bound,
        }),
        None => Ok(()),
    }
}

/// Checks an observation's content against its task and the magnitudes the receiver accepts
/// for it (usually `task.magnitudes`; a planner's operator may configure others), and the task's
/// observation bounds where its spec declares them. Not its place in the episode: the
/// planner's agent session checks ordering.
pub fn validate_observation(
    msg: &Observation,
    task: &TaskSpec,
    magnitudes: &Magnitudes,
) -> Result<(), ValidationError> {
    check_vector("observation", task, &msg.obs, task.obs_dim)?;
    check_magnitude("observation", &msg.obs, magnitudes.observation)?;
    if let Some(bounds) = &task.observation_bounds {
        let outside = msg
            .obs
            .iter()
            .zip(bounds.low.iter().zip(&bounds.high))
            .position(|(v, (lo, hi))| v < lo || v > hi);
        if let Some(index) = outside {
            return Err(ValidationError::ObservationOutOfBounds {
                index,
                value: msg.obs[index],
                low: bounds.low[index],
                high: bounds.high[index],
            });
        }
    }
    if let Some(applied) = &msg.applied {
        if msg.step == 0 {
            return Err(ValidationError::AppliedAtReset);
        }
        check_applied(applied, task)?;
    }
    match (msg.step, msg.reward) {
        (0, Some(_)) => Err(ValidationError::RewardAtReset),
        (0, None) => Ok(()),
        (step, None) => Err(ValidationError::MissingReward(step)),
        (_, Some(r)) if !r.is_finite() => Err(ValidationError::NonFiniteReward(r)),
        (_, Some(r)) => check_magnitude("reward", &[r], magnitudes.reward),
    }
}

/// Checks the action an agent says it applied: the task's dimension, finite, and within the
/// action bounds (a real actuator cannot apply more than its limits, so a value outside them is
/// a broken sender, and storing it would teach the models transitions no agent can make).
fn check_applied(applied: &[f32], task: &TaskSpec) -> Result<(), ValidationError> {
    check_vector("applied action", task, applied, task.act_dim)?;
    let bounds = task.action_low.iter().zip(&task.action_high);
    match applied
        .iter()
        .zip(bounds)
        .position(|(v, (lo, hi))| v < lo || v > hi)
    {
        Some(index) => Err(ValidationError::AppliedOutOfRange {
            index,
            value: applied[index],
            low: task.action_low[index],
            high: task.action_high[index],
        }),
        None => Ok(()),
    }
}

/// Checks an action's content against its task (bounds are the simulator's to enforce by
/// clamping; a planner never sends out-of-bounds actions).
pub fn validate_action(msg: &Action, task: &TaskSpec) -> Result<(), ValidationError> {
    check_vector("action", task, &msg.action, task.act_dim)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::{Builtin, ObservationBounds};

    fn obs(step: u32, values: Vec<f32>, reward: Option<f32>) -> Observation {
        Observation::new(0, step, values, reward, None)
    }

    #[test]
    fn accepts_well_formed_observations() {
        let task = Builtin::Cartpole.task();
        let m = &task.magnitudes;
        validate_observation(&obs(0, vec![0.0; 4], None), task, m).unwrap();
        validate_observation(&obs(5, vec![0.0; 4], Some(0.3)), task, m).unwrap();
        // The bound itself is allowed.
        validate_observation(&obs(5, vec![m.observation; 4], Some(-m.reward)), task, m).unwrap();
        for bound in [-3.0, 0.5, 3.0] {
            let applied = obs(5, vec![0.0; 4], Some(0.3)).with_applied(vec![bound]);
            validate_observation(&applied, task, m).unwrap();
        }
    }

    #[test]
    fn rejects_bad_observations_with_codes() {
        let task = Builtin::Cartpole.task();
        let cases = [
            (obs(0, vec![0.0; 3], None), ErrorCode::Dimension),
            (
                obs(0, vec![0.0, f32::NAN, 0.0, 0.0], None),
                ErrorCode::NonFinite,
            ),
            (
                obs(1, vec![0.0, 0.0, f32::INFINITY, 0.0], Some(0.0)),
                ErrorCode::NonFinite,
            ),
            (obs(1, vec![0.0; 4], Some(f32::NAN)), ErrorCode::NonFinite),
            (obs(1, vec![0.0; 4], None), ErrorCode::OutOfOrder),
            (obs(0, vec![0.0; 4], Some(1.0)), ErrorCode::OutOfOrder),
            (
                obs(0, vec![0.0; 4], None).with_applied(vec![0.0]),
                ErrorCode::OutOfOrder,
            ),
            (
                obs(1, vec![0.0; 4], Some(0.0)).with_applied(vec![0.0, 0.0]),
                ErrorCode::Dimension,
            ),
            (
                obs(1, vec![0.0; 4], Some(0.0)).with_applied(vec![]),
                ErrorCode::Dimension,
            ),
            (
                obs(1, vec![0.0; 4], Some(0.0)).with_applied(vec![f32::NAN]),
                ErrorCode::NonFinite,
            ),
            (
                obs(1, vec![0.0; 4], Some(0.0)).with_applied(vec![f32::NEG_INFINITY]),
                ErrorCode::NonFinite,
            ),
            (
                obs(1, vec![0.0; 4], Some(0.0)).with_applied(vec![3.001]),
                ErrorCode::OutOfRange,
            ),
            (
                obs(1, vec![0.0; 4], Some(0.0)).with_applied(vec![-1e30]),
                ErrorCode::OutOfRange,
            ),
            (
                obs(0, vec![0.0, f32::MAX, 0.0, 0.0], None),
                ErrorCode::OutOfRange,
            ),
            (
                obs(0, vec![0.0, 0.0, 0.0, -3.4e38], None),
                ErrorCode::OutOfRange,
            ),
            (
                obs(0, vec![1.0001e4, 0.0, 0.0, 0.0], None),
                ErrorCode::OutOfRange,
            ),
            (obs(1, vec![0.0; 4], Some(f32::MIN)), ErrorCode::OutOfRange),
            (obs(1, vec![0.0; 4], Some(2e4)), ErrorCode::OutOfRange),
        ];
        for (msg, code) in cases {
            let err = validate_observation(&msg, task, &task.magnitudes).unwrap_err();
            assert_eq!(err.code(), code, "{err}");
            assert!(!err.to_string().is_empty());
        }
        let err =
            validate_observation(&obs(0, vec![0.0; 5], None), task, &task.magnitudes).unwrap_err();
        assert_eq!(
            err.to_string(),
            "observation has 5 numbers, task cartpole needs 4"
        );
        let err = validate_observation(
            &obs(0, vec![0.0, 0.0, 5e5, 0.0], None),
            task,
            &task.magnitudes,
        )
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "observation[2] is 5e5, beyond this task's bound of ±1e4"
        );
        // A custom bound (a robot with larger readings) admits what the catalog's refuses.
        let wide = Magnitudes {
            observation: 1e6,
            reward: 1e4,
        };
        validate_observation(&obs(0, vec![0.0, 0.0, 5e5, 0.0], None), task, &wide).unwrap();
    }

    /// A spec's observation bounds refuse what lies outside them, on top of the magnitudes.
    #[test]
    fn declared_observation_bounds_are_enforced() {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "bounded-cartpole".into();
        spec.observation_bounds = Some(ObservationBounds {
            low: vec![-2.4, -1e3, -10.0, -10.0],
            high: vec![2.4, 1e3, 10.0, 10.0],
        });
        let task = crate::task::Task::intern(spec, &Default::default()).unwrap();
        let m = &task.magnitudes;
        validate_observation(&obs(0, vec![2.4, 0.0, 0.0, -10.0], None), task, m).unwrap();
        let err =
            validate_observation(&obs(0, vec![2.5, 0.0, 0.0, 0.0], None), task, m).unwrap_err();
        assert_eq!(err.code(), ErrorCode::OutOfRange);
        assert_eq!(
            err.to_string(),
            "observation[0] is 2.5, outside the task's observation bounds [-2.4, 2.4]"
        );
    }
}
