//! What one planner knows of the fleet's other planners: the live ones (with their pins, once
//! fetched), from Zenoh liveliness. It decides *preference* only (which planner should take a
//! free run); etcd alone decides ownership (see [`super::etcd`]). Pure data, so the placement
//! rule is tested without a network.
//!
//! The rule, the same on every planner: **a free run is preferred on the planner that
//! rendezvous hashing picks among the live planners whose pins allow it.** A planner that
//! comes back therefore changes only the preference for free runs, never who holds a run.
//!
//! Liveliness tokens can be declared by anyone the router lets through, so what they say is
//! bounded: names must be valid, and at most [`MAX_PLANNERS`] are kept (further ones are
//! ignored until some leave).

use super::placement;
use crate::config::Pins;
use std::collections::BTreeMap;

/// Most planners one planner keeps track of.
pub const MAX_PLANNERS: usize = 256;

/// Who a free run is preferred on, as this planner sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Owner {
    /// `planner` holds the run's owner key in etcd, created at fencing token `epoch`.
    Holder { planner: String, epoch: u64 },
    /// Nobody holds it; rendezvous hashing places it on `planner`.
    Placed { planner: String },
    /// No live planner may own it (every one's pins exclude it).
    Nobody,
}

impl Owner {
    /// The owning (or preferred) planner, if any.
    pub fn planner(&self) -> Option<&str> {
        match self {
            Owner::Holder { planner, .. } | Owner::Placed { planner } => Some(planner),
            Owner::Nobody => None,
        }
    }
}

/// The live planners.
#[derive(Clone, Debug, Default)]
pub struct View {
    /// Live planners; `None` until their pins are known (they count as allowing every run
    /// meanwhile, so a planner is never left out for lack of an answer).
    planners: BTreeMap<String, Option<Pins>>,
}

impl View {
    /// A planner token appeared (pins not known yet), unless it is already known, its name is
    /// not a valid name, or [`MAX_PLANNERS`] are known already. Returns whether it was added.
    pub fn planner_joined(&mut self, planner: &str) -> bool {
        if self.planners.contains_key(planner)
            || self.planners.len() >= MAX_PLANNERS
            || proto::validate_name(planner).is_err()
        {
            return false;
        }
        self.planners.insert(planner.to_string(), None);
        true
    }

    /// A planner's pins arrived.
    pub fn set_pins(&mut self, planner: &str, pins: Pins) {
        if let Some(slot) = self.planners.get_mut(planner) {
            *slot = Some(pins);
        }
    }

    /// A planner token went away.
    pub fn planner_left(&mut self, planner: &str) -> bool {
        self.planners.remove(planner).is_some()
    }

    /// The live planners, by id.
    pub fn planners(&self) -> impl Iterator<Item = &str> {
        self.planners.keys().map(String::as_str)
    }

    /// The planner a free `run` is preferred on.
    pub fn placed(&self, run: &str) -> Owner {
        let candidates = self
            .planners
            .iter()
            .filter(|(_, pins)| pins.as_ref().is_none_or(|p| p.allows(run)))
            .map(|(id, _)| id.as_str());
        match placement::place(run, candidates) {
            Some(planner) => Owner::Placed {
                planner: planner.to_string(),
            },
            None => Owner::Nobody,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(planners: &[&str]) -> View {
        let mut v = View::default();
        for p in planners {
            v.planner_joined(p);
        }
        v
    }

    #[test]
    fn pins_exclude_planners_and_unknown_pins_allow_everything() {
        let mut v = view(&["pa", "pb"]);
        v.set_pins(
            "pa",
            Pins {
                serve: vec!["ant-*".into()],
                refuse: vec![],
            },
        );
        for i in 0..50 {
            assert_eq!(v.placed(&format!("cartpole-{i}")).planner(), Some("pb"));
        }
        v.set_pins(
            "pb",
            Pins {
                serve: vec![],
                refuse: vec!["cartpole-*".into()],
            },
        );
        assert_eq!(v.placed("cartpole-1"), Owner::Nobody);
        assert!(v.planner_left("pb"));
        assert!(!v.planner_left("pb"));
        v.planner_joined("pc");
        assert_eq!(v.placed("cartpole-1").planner(), Some("pc"));
        assert!(!v.planner_joined("pc"), "a second Put changes nothing");
    }

    /// Forged planner tokens cannot grow the view without bound, nor add names that are not
    /// names.
    #[test]
    fn the_view_keeps_valid_names_only_and_at_most_its_bound() {
        let mut v = View::default();
        assert!(!v.planner_joined("a/b"));
        assert!(!v.planner_joined("**"));
        assert!(!v.planner_joined(""));
        for i in 0..10_000 {
            v.planner_joined(&format!("forged-{i}"));
        }
        assert_eq!(v.planners().count(), MAX_PLANNERS);
        assert!(!v.planner_joined("late"));
        assert!(v.planner_left("forged-0"));
        assert!(v.planner_joined("late"));
    }
}
