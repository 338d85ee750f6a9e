//! What one planner knows of the fleet: the live planners (with their pins, once fetched) and
//! the live run leases, both from Zenoh liveliness. Pure data, so the ownership rule is tested
//! without a network.
//!
//! The rule, the same on every planner: **a run belongs to the live holder of its newest lease;
//! a run without one belongs to the planner that rendezvous hashing picks among the live
//! planners whose pins allow it.** A planner that comes back therefore takes nothing from a
//! live holder; runs only move when their holder goes (dies, stops, or steps down).

use super::placement;
use crate::config::Pins;
use std::collections::BTreeMap;

/// Who owns a run, as this planner sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Owner {
    /// `planner` holds the run's lease at `epoch`.
    Holder { planner: String, epoch: u64 },
    /// Nobody holds it; rendezvous hashing places it on `planner`.
    Placed { planner: String },
    /// No live planner may own it (every one's pins exclude it).
    Nobody,
}

impl Owner {
    /// The owning planner, if any.
    pub fn planner(&self) -> Option<&str> {
        match self {
            Owner::Holder { planner, .. } | Owner::Placed { planner } => Some(planner),
            Owner::Nobody => None,
        }
    }
}

/// The live planners and leases.
#[derive(Clone, Debug, Default)]
pub struct View {
    /// Live planners; `None` until their pins are known (they count as allowing every run
    /// meanwhile, so a planner is never left out for lack of an answer).
    planners: BTreeMap<String, Option<Pins>>,
    /// Live leases: run → epoch → planner.
    leases: BTreeMap<String, BTreeMap<u64, String>>,
}

impl View {
    /// A planner token appeared (pins not known yet), unless it is already known.
    pub fn planner_joined(&mut self, planner: &str) -> bool {
        if self.planners.contains_key(planner) {
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

    pub fn lease_taken(&mut self, run: &str, epoch: u64, planner: &str) {
        self.leases
            .entry(run.to_string())
            .or_default()
            .insert(epoch, planner.to_string());
    }

    pub fn lease_dropped(&mut self, run: &str, epoch: u64, planner: &str) {
        if let Some(held) = self.leases.get_mut(run) {
            if held.get(&epoch).is_some_and(|p| p == planner) {
                held.remove(&epoch);
            }
            if held.is_empty() {
                self.leases.remove(run);
            }
        }
    }

    /// The live planners, by id.
    pub fn planners(&self) -> impl Iterator<Item = &str> {
        self.planners.keys().map(String::as_str)
    }

    /// The owner of `run` by the rule in the module's docs.
    pub fn owner(&self, run: &str) -> Owner {
        if let Some((epoch, planner)) = self.leases.get(run).and_then(|l| l.last_key_value()) {
            return Owner::Holder {
                planner: planner.clone(),
                epoch: *epoch,
            };
        }
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
    fn a_live_holder_keeps_its_run_and_its_departure_frees_it() {
        let mut v = view(&["pa", "pb", "pc"]);
        let placed = v.owner("r").planner().unwrap().to_string();
        let holder = if placed == "pa" { "pb" } else { "pa" };
        v.lease_taken("r", 3, holder);
        assert_eq!(
            v.owner("r"),
            Owner::Holder {
                planner: holder.into(),
                epoch: 3
            }
        );
        // A newer lease wins over an older one still visible.
        v.lease_taken("r", 4, "pc");
        assert_eq!(v.owner("r").planner(), Some("pc"));
        v.lease_dropped("r", 4, "pc");
        v.lease_dropped("r", 3, holder);
        assert_eq!(v.owner("r"), Owner::Placed { planner: placed });
        // A drop that names another holder changes nothing.
        v.lease_taken("r", 5, "pa");
        v.lease_dropped("r", 5, "pb");
        assert_eq!(v.owner("r").planner(), Some("pa"));
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
            assert_eq!(v.owner(&format!("cartpole-{i}")).planner(), Some("pb"));
        }
        v.set_pins(
            "pb",
            Pins {
                serve: vec![],
                refuse: vec!["cartpole-*".into()],
            },
        );
        assert_eq!(v.owner("cartpole-1"), Owner::Nobody);
        assert!(v.planner_left("pb"));
        assert!(!v.planner_left("pb"));
        v.planner_joined("pc");
        assert_eq!(v.owner("cartpole-1").planner(), Some("pc"));
        assert!(!v.planner_joined("pc"), "a second Put changes nothing");
    }
}
