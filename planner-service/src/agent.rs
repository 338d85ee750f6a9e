//! One agent's place in its episode: the state machine that turns a stream of observations
//! into transitions `(s, a, s')` and refuses observations that do not follow on.
//!
//! The planner knows the action it sent for step `t`, so the observation of step `t + 1`
//! completes the transition. Everything is checked before anything is stored: a message out of
//! order is reported to the sender and changes nothing.

use crate::replay::{ActionOrigin, EpisodeSummary};
use proto::{EpisodeEnd, ErrorCode, ErrorReport, Observation};

/// What an accepted observation means for the run.
#[derive(Debug, PartialEq)]
pub struct Accepted {
    /// The transition this observation completes: `(s, a, origin, reward)`, with `s'` the
    /// observation and `a` the action the agent says it applied, or else the one planned.
    pub transition: Option<(Vec<f32>, Vec<f32>, ActionOrigin, f32)>,
    /// The episode this observation ended, if it did.
    pub finished: Option<EpisodeSummary>,
    /// An earlier episode this one replaced before it finished (the agent restarted).
    pub abandoned: Option<EpisodeSummary>,
}

impl Accepted {
    /// Whether the agent waits for an action (every observation except an episode's last).
    pub fn needs_action(&self) -> bool {
        self.finished.is_none()
    }
}

#[derive(Clone, Debug)]
struct Episode {
    number: u32,
    /// The step of the last observation accepted.
    step: u32,
    obs: Vec<f32>,
    /// The action sent for `step`, once sent.
    action: Option<Vec<f32>>,
    episode_return: f32,
}

/// What an agent at `step` of `episode` must send next to end that episode within the task's
/// episode length of `last` steps (the text of the error refusing a step past it).
fn what_ends(episode: u32, step: u32, last: u32) -> String {
    if step + 1 == last {
        format!(
            "send step {last} of episode {episode} with `end` set (`time_limit`, or `terminated`)"
        )
    } else {
        format!(
            "send step {} of episode {episode} next, and end the episode (`end`) at step {last} at the latest",
            step + 1
        )
    }
}

/// One agent of a run. Cloned to try an observation before committing to it (see
/// [`crate::run::Run::accept`]).
#[derive(Clone, Debug)]
pub struct AgentSession {
    name: String,
    /// The task's episode length: no step beyond it is accepted, so an agent that never ends
    /// its episode cannot grow one without bound.
    episode_len: u32,
    current: Option<Episode>,
    /// The last episode number seen; new episodes must be numbered above it.
    last_episode: Option<u32>,
    episodes_finished: u32,
    last_return: Option<f32>,
}

impl AgentSession {
    pub fn new(name: impl Into<String>, episode_len: u32) -> Self {
        Self {
            name: name.into(),
            episode_len,
            current: None,
            last_episode: None,
            episodes_finished: 0,
            last_return: None,
        }
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn episodes_finished(&self) -> u32 {
        self.episodes_finished
    }

    pub fn last_return(&self) -> Option<f32> {
        self.last_return
    }

    /// The episode in progress and the step of its last observation.
    pub fn position(&self) -> Option<(u32, u32)> {
        self.current.as_ref().map(|e| (e.number, e.step))
    }

    /// Takes a validated observation (dimensions and finiteness are checked by
    /// [`proto::validate`] before this).
    pub fn observe(&mut self, msg: &Observation) -> Result<Accepted, ErrorReport> {
        let out_of_order =
            |why: String| ErrorReport::new(ErrorCode::OutOfOrder, why).at(msg.episode, msg.step);
        if msg.step == 0 {
            if msg.episode == u32::MAX {
                return Err(out_of_order(format!(
                    "episode numbers must stay below {}, so that a next episode exists",
                    u32::MAX
                )));
            }
            if msg.end.is_some() {
                return Err(out_of_order("an episode cannot end at step 0".into()));
            }
            if let Some(last) = self.last_episode
                && msg.episode <= last
            {
                return Err(out_of_order(format!(
                    "episode {} starts, but episode {last} was already seen: number episodes upwards",
                    msg.episode
                )));
            }
            let abandoned = self
                .current
                .take()
                .map(|e| self.summary(e, EpisodeEnd::Interrupted));
            self.last_episode = Some(msg.episode);
            self.current = Some(Episode {
                number: msg.episode,
                step: 0,
                obs: msg.obs.clone(),
                action: None,
                episode_return: 0.0,
            });
            return Ok(Accepted {
                transition: None,
                finished: None,
                abandoned,
            });
        }
        let Some(current) = self.current.as_mut() else {
            return Err(out_of_order(format!(
                "step {} of episode {} arrived with no episode in progress: start with step 0",
                msg.step, msg.episode
            )));
        };
        let last = self.episode_len;
        if msg.step > last && msg.episode == current.number {
            return Err(out_of_order(format!(
                "step {} is beyond this task's episode length of {last} steps: episode {} is at step {}; {}",
                msg.step,
                current.number,
                current.step,
                what_ends(current.number, current.step, last)
            )));
        }
        if msg.episode != current.number || msg.step != current.step + 1 {
            return Err(out_of_order(format!(
                "expected episode {} step {}, got episode {} step {}",
                current.number,
                current.step + 1,
                msg.episode,
                msg.step
            )));
        }
        if msg.step == last && msg.end.is_none() {
            return Err(out_of_order(format!(
                "step {last} is the last of this task's episode (length {last} steps) and must end it: \
                 send step {last} of episode {} again with `end` set (`time_limit`, or `terminated` \
                 if the task's termination fired); nothing of this message was stored",
                current.number
            )));
        }
        let Some(planned) = current.action.take() else {
            return Err(out_of_order(format!(
                "step {} arrived before the action for step {} was sent",
                msg.step, current.step
            )));
        };
        let (action, origin) = match &msg.applied {
            Some(applied) => (applied.clone(), ActionOrigin::Applied),
            None => (planned, ActionOrigin::Planned),
        };
        let reward = msg.reward.expect("validated: steps after 0 carry a reward");
        let obs = std::mem::replace(&mut current.obs, msg.obs.clone());
        current.step = msg.step;
        current.episode_return += reward;
        let finished = match msg.end {
            Some(end) => {
                let episode = self.current.take().expect("in progress");
                Some(self.summary(episode, end))
            }
            None => None,
        };
        Ok(Accepted {
            transition: Some((obs, action, origin, reward)),
            finished,
            abandoned: None,
        })
    }

    /// Records the action sent for the current step.
    pub fn acted(&mut self, step: u32, action: &[f32]) {
        if let Some(current) = self.current.as_mut()
            && current.step == step
        {
            current.action = Some(action.to_vec());
        }
    }

    /// Ends the episode in progress as interrupted (the agent vanished).
    pub fn interrupt(&mut self) -> Option<EpisodeSummary> {
        let episode = self.current.take()?;
        Some(self.summary(episode, EpisodeEnd::Interrupted))
    }

    fn summary(&mut self, e: Episode, end: EpisodeEnd) -> EpisodeSummary {
        if end != EpisodeEnd::Interrupted {
            self.episodes_finished += 1;
            self.last_return = Some(e.episode_return);
        }
        EpisodeSummary {
            agent: self.name.clone(),
            episode: e.number,
            steps: e.step,
            episode_return: e.episode_return,
            end,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn obs(
        episode: u32,
        step: u32,
        x: f32,
        reward: Option<f32>,
        end: Option<EpisodeEnd>,
    ) -> Observation {
        Observation::new(episode, step, vec![x; 4], reward, end)
    }

    #[test]
    fn an_episode_yields_its_transitions_and_return() {
        let mut s = AgentSession::new("a", 200);
        let first = s.observe(&obs(0, 0, 0.0, None, None)).unwrap();
        assert_eq!(first.transition, None);
        assert!(first.needs_action());
        s.acted(0, &[1.0]);
        let second = s.observe(&obs(0, 1, 1.0, Some(0.5), None)).unwrap();
        assert_eq!(
            second.transition,
            Some((vec![0.0; 4], vec![1.0], ActionOrigin::Planned, 0.5))
        );
        s.acted(1, &[2.0]);
        // The agent clipped the planned 2.0 to 1.5: the transition holds what it applied.
        let last = s
            .observe(
                &obs(0, 2, 2.0, Some(0.25), Some(EpisodeEnd::TimeLimit)).with_applied(vec![1.5]),
            )
            .unwrap();
        assert_eq!(
            last.transition,
            Some((vec![1.0; 4], vec![1.5], ActionOrigin::Applied, 0.25))
        );
        assert!(!last.needs_action());
        let summary = last.finished.unwrap();
        assert_eq!(
            (summary.steps, summary.episode_return, summary.end),
            (2, 0.75, EpisodeEnd::TimeLimit)
        );
        assert_eq!(s.episodes_finished(), 1);
        assert_eq!(s.position(), None);
    }

    #[test]
    fn out_of_order_messages_are_refused_without_changing_state() {
        let mut s = AgentSession::new("a", 200);
        let err = s.observe(&obs(0, 3, 0.0, Some(0.0), None)).unwrap_err();
        assert_eq!(err.code, ErrorCode::OutOfOrder);
        s.observe(&obs(0, 0, 0.0, None, None)).unwrap();
        // No action sent yet for step 0.
        assert_eq!(
            s.observe(&obs(0, 1, 0.0, Some(0.0), None))
                .unwrap_err()
                .code,
            ErrorCode::OutOfOrder
        );
        s.acted(0, &[0.0]);
        // Skipped step, wrong episode, repeated step.
        for bad in [
            obs(0, 2, 0.0, Some(0.0), None),
            obs(1, 1, 0.0, Some(0.0), None),
            obs(0, 0, 0.0, None, None),
        ] {
            assert_eq!(
                s.observe(&bad).unwrap_err().code,
                ErrorCode::OutOfOrder,
                "{bad:?}"
            );
        }
        assert_eq!(s.position(), Some((0, 0)));
        assert!(s.observe(&obs(0, 1, 1.0, Some(1.0), None)).is_ok());
    }

    #[test]
    fn a_restarted_episode_abandons_the_old_one() {
        let mut s = AgentSession::new("a", 200);
        s.observe(&obs(4, 0, 0.0, None, None)).unwrap();
        s.acted(0, &[0.0]);
        s.observe(&obs(4, 1, 0.0, Some(1.0), None)).unwrap();
        let restart = s.observe(&obs(5, 0, 0.0, None, None)).unwrap();
        let abandoned = restart.abandoned.unwrap();
        assert_eq!(
            (abandoned.episode, abandoned.end),
            (4, EpisodeEnd::Interrupted)
        );
        assert_eq!(s.episodes_finished(), 0);
        assert_eq!(
            s.observe(&obs(3, 0, 0.0, None, None)).unwrap_err().code,
            ErrorCode::OutOfOrder
        );
    }

    /// No step beyond the task's episode length is accepted, and the last step must end the
    /// episode; a refused step leaves the episode where it was, and the error says what to send.
    #[test]
    fn steps_beyond_the_episode_length_are_refused() {
        let mut s = AgentSession::new("a", 2);
        s.observe(&obs(0, 0, 0.0, None, None)).unwrap();
        s.acted(0, &[0.0]);
        s.observe(&obs(0, 1, 0.0, Some(1.0), None)).unwrap();
        s.acted(1, &[0.0]);
        for step in [3, u32::MAX] {
            let err = s.observe(&obs(0, step, 0.0, Some(1.0), None)).unwrap_err();
            assert_eq!(err.code, ErrorCode::OutOfOrder);
            assert!(err.message.contains("episode length of 2"), "{err}");
            assert!(
                err.message.contains("send step 2 of episode 0 with `end`"),
                "{err}"
            );
        }
        assert_eq!(s.position(), Some((0, 1)));
        // Ending the episode (or starting the next) is still accepted.
        assert!(s.observe(&obs(1, 0, 0.0, None, None)).is_ok());
    }

    /// A task of 200 steps: steps 0..=199, then step 200 without `end` is refused and says to
    /// send it again with `end`; step 201 is refused the same way; step 200 with `end` ends the
    /// episode (the sequence that used to leave an episode that could never end).
    #[test]
    fn the_last_step_must_end_the_episode_and_the_error_says_how() {
        let mut s = AgentSession::new("a", 200);
        s.observe(&obs(0, 0, 0.0, None, None)).unwrap();
        s.acted(0, &[0.0]);
        for step in 1..200 {
            s.observe(&obs(0, step, 0.0, Some(1.0), None)).unwrap();
            s.acted(step, &[0.0]);
        }
        let err = s.observe(&obs(0, 200, 0.0, Some(1.0), None)).unwrap_err();
        assert_eq!(err.code, ErrorCode::OutOfOrder);
        assert_eq!((err.episode, err.step), (Some(0), Some(200)));
        assert!(
            err.message
                .contains("send step 200 of episode 0 again with `end` set (`time_limit`"),
            "{err}"
        );
        assert_eq!(s.position(), Some((0, 199)), "nothing moved");
        for end in [None, Some(EpisodeEnd::TimeLimit)] {
            let err = s.observe(&obs(0, 201, 0.0, Some(1.0), end)).unwrap_err();
            assert!(
                err.message
                    .contains("send step 200 of episode 0 with `end` set"),
                "{err}"
            );
        }
        let last = s
            .observe(&obs(0, 200, 0.0, Some(1.0), Some(EpisodeEnd::TimeLimit)))
            .unwrap();
        let summary = last.finished.expect("the episode ended");
        assert_eq!((summary.steps, summary.end), (200, EpisodeEnd::TimeLimit));
        assert_eq!(s.episodes_finished(), 1);
        assert!(s.observe(&obs(1, 0, 0.0, None, None)).is_ok());
    }

    #[test]
    fn the_last_episode_number_is_refused_so_that_a_next_one_exists() {
        let mut s = AgentSession::new("a", 200);
        let err = s.observe(&obs(u32::MAX, 0, 0.0, None, None)).unwrap_err();
        assert_eq!(err.code, ErrorCode::OutOfOrder);
        assert!(err.message.contains("below"), "{}", err.message);
        s.observe(&obs(u32::MAX - 1, 0, 0.0, None, None)).unwrap();
    }
}
