//! A fleet of planners behind one router: exactly one owner per run, and handover when an
//! owner goes.
//!
//! ```text
//! {prefix}/alive/planners/{id}             liveliness: the live planners (the candidates)
//! {prefix}/planners/{id}/fleet             queryable: each planner's pins (JSON)
//! {prefix}/alive/leases/{run}/{epoch}/{id} liveliness: planner `id` owns `run` at `epoch`
//! {data_dir}/runs/{run}/epochs/{epoch}     the fence: created exclusively by each new owner
//! ```
//!
//! Every planner watches the planner and lease tokens (a liveliness subscriber plus an
//! initial `get`) and applies the same rule ([`view`]): the live holder of a run's newest
//! lease owns it; a free run goes to the planner that rendezvous hashing ([`placement`])
//! picks among the live planners its pins ([`crate::config::Pins`]) allow. Only the owner answers the run's
//! attach queries and handles its observations; the others stay silent, so an agent's query
//! gets exactly one answer.
//!
//! Taking a run ([`Fleet::take`]) creates the next epoch's file in the shared run directory
//! (exclusively: two planners never hold one epoch), then declares the lease token. The epoch
//! is written into the replay log and every action; an owner checks on disk that its epoch is
//! still the newest before it writes at episode boundaries and checkpoints, and steps down when
//! it is not. Zenoh's liveliness is the lease: a planner that dies or loses the router loses
//! its tokens, and the next owner by the rule takes the run over from the shared directory.
//! `docs/fleet.md` discusses the choice and its failure modes.
//!
//! A daemon with no `[fleet]` in its configuration is alone ([`Fleet::alone`]): it owns every
//! run it serves, subscribes to no planner or lease token and declares no lease, so a token any
//! client can declare (a forged lease of the highest epoch, thousands of forged planners) never
//! reaches it. It still claims each run's epoch on disk, which fences a second daemon started on
//! the same data directory by mistake.

pub mod placement;
pub mod view;

use crate::config::Pins;
pub use view::{Owner, View};

use crate::persist::{PersistError, RunDir};
use proto::Keys;
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::sync::mpsc;
use zenoh::Wait;
use zenoh::liveliness::LivelinessToken;
use zenoh::sample::{Sample, SampleKind};

/// Ownership events kept for `status`.
const EVENTS_KEPT: usize = 50;

/// How long a peer's pins may take to arrive.
const PINS_TIMEOUT: Duration = Duration::from_secs(5);

/// Largest pins reply read from a peer (a hostile or broken peer cannot make us allocate more).
const MAX_PINS_BYTES: usize = 64 * 1024;

/// Failures of the fleet machinery.
#[derive(Debug, thiserror::Error)]
pub enum FleetError {
    #[error("zenoh ({what}): {reason}")]
    Zenoh { what: String, reason: String },
    #[error(transparent)]
    Persist(#[from] PersistError),
}

fn zenoh_err(what: &str) -> impl FnOnce(zenoh::Error) -> FleetError + '_ {
    move |e| FleetError::Zenoh {
        what: what.to_string(),
        reason: e.to_string(),
    }
}

/// Something that happened to the fleet or to a run's ownership, shown by `status`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct FleetEvent {
    /// Seconds since the Unix epoch.
    pub at_unix_s: f64,
    #[serde(flatten)]
    pub kind: FleetEventKind,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum FleetEventKind {
    /// This planner took `run` over at `epoch`; `previous` held the epoch before (if any).
    Took {
        run: String,
        epoch: u64,
        previous: Option<String>,
    },
    /// This planner gave `run` up: another planner owns it now.
    SteppedDown {
        run: String,
        epoch: u64,
        reason: String,
    },
    PlannerJoined {
        planner: String,
    },
    PlannerLeft {
        planner: String,
    },
}

/// What `status` shows of the fleet.
#[derive(Clone, Debug, Serialize, Deserialize, schemars::JsonSchema)]
pub struct FleetStatus {
    /// The live planners this planner sees, itself included.
    pub planners: Vec<String>,
    pub pins: Pins,
    /// The most recent ownership events, oldest first.
    pub events: Vec<FleetEvent>,
}

/// This planner's membership of the fleet.
pub struct Fleet {
    me: String,
    pins: Pins,
    keys: Keys,
    session: zenoh::Session,
    view: Mutex<View>,
    /// The leases this planner holds: run → (epoch, token; `None` for a planner alone).
    held: Mutex<HashMap<String, (u64, Option<LivelinessToken>)>>,
    /// No `[fleet]` is configured: this planner owns every run it serves and reads no token.
    alone: bool,
    events: Mutex<VecDeque<FleetEvent>>,
    /// Runs whose owner found itself fenced; the service steps down from them.
    fenced: Mutex<Vec<String>>,
    changed: mpsc::UnboundedSender<()>,
}

/// Wakes the service whenever the view changed or a run was fenced: it then rebalances.
pub type Changes = mpsc::UnboundedReceiver<()>;

impl Fleet {
    /// Joins the fleet: serves this planner's pins, watches the planner and lease tokens and
    /// reads the ones already declared, so the view is complete when this returns. (The
    /// planner's own liveliness token is the service's to declare.)
    pub async fn join(
        session: zenoh::Session,
        keys: Keys,
        me: String,
        pins: Pins,
    ) -> Result<(Arc<Self>, Changes), FleetError> {
        let (fleet, changes) = Self::new(session, keys, me, pins, false);
        let profile = serde_json::to_vec(&fleet.pins).expect("pins serialise");
        fleet
            .session
            .declare_queryable(fleet.keys.planner_fleet(&fleet.me))
            .callback(move |query| {
                let key = query.key_expr().clone();
                if let Err(e) = query
                    .reply(key, profile.clone())
                    .encoding(zenoh::bytes::Encoding::APPLICATION_JSON)
                    .wait()
                {
                    tracing::warn!(error = %e, "fleet profile reply failed");
                }
            })
            .background()
            .await
            .map_err(zenoh_err("declaring the fleet profile queryable"))?;
        let runtime = tokio::runtime::Handle::current();
        for key in [fleet.keys.all_planners_alive(), fleet.keys.all_leases()] {
            let weak = Arc::downgrade(&fleet);
            let handle = runtime.clone();
            fleet
                .session
                .liveliness()
                .declare_subscriber(&key)
                .callback(move |sample| {
                    if let Some(fleet) = weak.upgrade() {
                        fleet.token(&sample, &handle);
                    }
                })
                .background()
                .await
                .map_err(zenoh_err("watching liveliness"))?;
            let replies = fleet
                .session
                .liveliness()
                .get(&key)
                .timeout(PINS_TIMEOUT)
                .await
                .map_err(zenoh_err("reading liveliness"))?;
            while let Ok(reply) = replies.recv_async().await {
                if let Ok(sample) = reply.result() {
                    fleet.token(sample, &runtime);
                }
            }
        }
        Ok((fleet, changes))
    }

    /// A planner alone (no `[fleet]` configured): it owns every run it serves, reads no
    /// planner or lease token and declares no lease. Only the fence on disk is kept.
    pub fn alone(session: zenoh::Session, keys: Keys, me: String) -> (Arc<Self>, Changes) {
        Self::new(session, keys, me, Pins::default(), true)
    }

    fn new(
        session: zenoh::Session,
        keys: Keys,
        me: String,
        pins: Pins,
        alone: bool,
    ) -> (Arc<Self>, Changes) {
        let (changed, changes) = mpsc::unbounded_channel();
        let mut view = View::default();
        view.planner_joined(&me);
        view.set_pins(&me, pins.clone());
        let fleet = Arc::new(Self {
            me,
            pins,
            keys,
            session,
            view: Mutex::new(view),
            held: Mutex::new(HashMap::new()),
            events: Mutex::new(VecDeque::new()),
            fenced: Mutex::new(Vec::new()),
            changed,
            alone,
        });
        (fleet, changes)
    }

    pub fn me(&self) -> &str {
        &self.me
    }

    /// Applies a planner or lease token's appearance or departure to the view.
    fn token(self: &Arc<Self>, sample: &Sample, runtime: &tokio::runtime::Handle) {
        let key = sample.key_expr().as_str();
        let put = sample.kind() == SampleKind::Put;
        if let Some(planner) = self.keys.parse_planner_alive(key) {
            if planner == self.me {
                return;
            }
            let changed = {
                let mut view = self.lock_view();
                if put {
                    view.planner_joined(planner)
                } else {
                    view.planner_left(planner)
                }
            };
            if !changed {
                return;
            }
            let planner = planner.to_string();
            if put {
                tracing::info!(%planner, "planner joined the fleet");
                self.event(FleetEventKind::PlannerJoined {
                    planner: planner.clone(),
                });
                runtime.spawn(self.clone().fetch_pins(planner));
            } else {
                tracing::info!(%planner, "planner left the fleet");
                self.event(FleetEventKind::PlannerLeft { planner });
            }
        } else if let Some((run, epoch, planner)) = self.keys.parse_lease(key) {
            let mut view = self.lock_view();
            if put {
                view.lease_taken(run, epoch, planner);
            } else {
                view.lease_dropped(run, epoch, planner);
            }
        } else {
            return;
        }
        let _ = self.changed.send(());
    }

    /// Asks `planner` for its pins; until they come it counts as allowing every run.
    async fn fetch_pins(self: Arc<Self>, planner: String) {
        let key = self.keys.planner_fleet(&planner);
        let pins = async {
            let replies = self
                .session
                .get(&key)
                .timeout(PINS_TIMEOUT)
                .await
                .map_err(|e| e.to_string())?;
            let reply = replies
                .recv_async()
                .await
                .map_err(|_| "no answer".to_string())?;
            let sample = reply.result().map_err(|e| format!("{e:?}"))?;
            let bytes = sample.payload().to_bytes();
            if bytes.len() > MAX_PINS_BYTES {
                return Err(format!("{} bytes of pins", bytes.len()));
            }
            let pins: Pins = serde_json::from_slice(&bytes).map_err(|e| e.to_string())?;
            pins.validate().map_err(|e| e.to_string())?;
            Ok::<_, String>(pins)
        }
        .await;
        match pins {
            Ok(pins) => {
                tracing::debug!(%planner, ?pins, "pins of a peer");
                self.lock_view().set_pins(&planner, pins);
                let _ = self.changed.send(());
            }
            Err(reason) => {
                tracing::warn!(%planner, %reason, "cannot read a planner's pins; it counts as serving every run");
            }
        }
    }

    fn lock_view(&self) -> std::sync::MutexGuard<'_, View> {
        self.view.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn event(&self, kind: FleetEventKind) {
        let at_unix_s = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs_f64())
            .unwrap_or(0.0);
        let mut events = self.events.lock().unwrap_or_else(PoisonError::into_inner);
        if events.len() == EVENTS_KEPT {
            events.pop_front();
        }
        events.push_back(FleetEvent { at_unix_s, kind });
    }

    /// Who owns `run` now, as this planner sees it (a planner alone sees only itself).
    pub fn owner(&self, run: &str) -> Owner {
        self.lock_view().owner(run)
    }

    /// Whether this planner owns `run` (holds its newest lease, or it is free and placed here).
    pub fn is_mine(&self, run: &str) -> bool {
        self.owner(run).planner() == Some(self.me.as_str())
    }

    /// Takes `run` over: claims the epoch after the newest in `dir` and declares the lease.
    /// Returns the epoch to open the run at.
    ///
    /// # Errors
    /// [`PersistError::EpochTaken`] when another planner claimed the same epoch first (it owns
    /// the run then), or the epoch files or the token could not be written.
    pub fn take(&self, run: &str, dir: &RunDir) -> Result<u64, FleetError> {
        let seen = dir.current_epoch()?;
        let previous = dir.epoch_holder(seen);
        let epoch = dir.claim_epoch_after(seen, &self.me)?;
        let token = if self.alone {
            None
        } else {
            let token = self
                .session
                .liveliness()
                .declare_token(self.keys.run_lease(run, epoch, &self.me))
                .wait()
                .map_err(zenoh_err("declaring a run lease"))?;
            Some(token)
        };
        self.lock_view().lease_taken(run, epoch, &self.me);
        self.held
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(run.to_string(), (epoch, token));
        tracing::info!(%run, epoch, previous = ?previous, "took the run");
        self.event(FleetEventKind::Took {
            run: run.to_string(),
            epoch,
            previous,
        });
        Ok(epoch)
    }

    /// Gives `run` up (its lease token goes), saying why.
    pub fn step_down(&self, run: &str, reason: String) {
        let held = self
            .held
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(run);
        if let Some((epoch, token)) = held {
            drop(token);
            self.lock_view().lease_dropped(run, epoch, &self.me);
            tracing::warn!(%run, epoch, %reason, "stepped down");
            self.event(FleetEventKind::SteppedDown {
                run: run.to_string(),
                epoch,
                reason,
            });
        }
    }

    /// An owner found on disk that it lost `run`: the service steps down at its next turn.
    pub fn report_fenced(&self, run: &str) {
        self.fenced
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(run.to_string());
        let _ = self.changed.send(());
    }

    /// The runs reported fenced since the last call.
    pub fn take_fenced(&self) -> Vec<String> {
        std::mem::take(&mut *self.fenced.lock().unwrap_or_else(PoisonError::into_inner))
    }

    pub fn status(&self) -> FleetStatus {
        FleetStatus {
            planners: self.lock_view().planners().map(str::to_string).collect(),
            pins: self.pins.clone(),
            events: self
                .events
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .iter()
                .cloned()
                .collect(),
        }
    }
}
