//! A fleet of planners sharing one data directory behind one router: exactly one owner per
//! run, decided by etcd, and handover when an owner goes.
//!
//! ```text
//! etcd     {prefix}/owners/{run}              the run's owner key, on its owner's lease; its
//!                                             create revision is the fencing token
//! zenoh    {prefix}/alive/planners/{id}       liveliness: the live planners (discovery only)
//! zenoh    {prefix}/planners/{id}/fleet       queryable: each planner's pins (JSON)
//! disk     {data_dir}/runs/{run}/epochs/{tok} the tokens each owner took the run at
//! ```
//!
//! **Who owns a run** is etcd's answer alone ([`etcd`]): the holder of the run's owner key,
//! created in a transaction only when absent and attached to its creator's lease. Zenoh
//! liveliness serves discovery only: which planners are up, and so which one a *free* run is
//! preferred on (rendezvous hashing over the live planners their pins ([`Pins`]) allow, [`view`]). A
//! planner cut off from the router sees no peers and prefers every free run, but the runs
//! other planners hold have owner keys, so it takes none of them; one cut off from etcd can
//! renew nothing and take nothing, and stops acknowledging before its lease can expire.
//!
//! **Fencing.** The key's create revision is the run's token: in every replay record, every
//! `Action` and `AttachAccepted` ("epoch" on the wire). An owner acknowledges a step only
//! while its lease is valid by its own clock and it still holds the key at that token
//! ([`Fleet::may_acknowledge`]); readers skip records of a token older than a claim before
//! them, and agents drop actions of a token older than the one they attached at.
//!
//! Without `[fleet]` the daemon is alone: it owns every run in its data directory, needs no
//! etcd, and takes each run at the next epoch file in the run's directory (as its token).
//! `docs/fleet.md` lists what is guaranteed under which failure.

pub mod etcd;
pub mod placement;
pub mod view;

pub use etcd::{EtcdError, EtcdOwners, LeaseStatus, LeaseTiming};
pub use view::{Owner, View};

use crate::config::{FleetConfig, Pins};
use crate::persist::{PersistError, RunDir};
use proto::Keys;
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::sync::Notify;
use zenoh::Wait;
use zenoh::sample::{Sample, SampleKind};

/// Ownership events kept for `status`.
const EVENTS_KEPT: usize = 50;

/// How long a peer's pins may take to arrive.
const PINS_TIMEOUT: Duration = Duration::from_secs(5);

/// Largest pins reply read from a peer (a hostile or broken peer cannot make us allocate more).
const MAX_PINS_BYTES: usize = 64 * 1024;

/// How often a fleet planner reads the owner keys from etcd.
const OWNERS_REFRESH: Duration = Duration::from_millis(500);

/// How long a free run may stay free before any planner takes it, not only the one it is
/// preferred on (that one may be cut off from etcd, or its pins may never arrive).
pub const FREE_GRACE: Duration = Duration::from_secs(3);

/// Failures of the fleet machinery.
#[derive(Debug, thiserror::Error)]
pub enum FleetError {
    #[error("zenoh ({what}): {reason}")]
    Zenoh { what: String, reason: String },
    #[error(transparent)]
    Persist(#[from] PersistError),
    #[error(transparent)]
    Etcd(#[from] EtcdError),
    #[error("{0}")]
    Task(String),
}

impl FleetError {
    /// Whether another planner owns the run (so its answer is the one an agent must get).
    pub fn is_contended(&self) -> bool {
        matches!(
            self,
            FleetError::Etcd(EtcdError::Owned { .. })
                | FleetError::Persist(PersistError::EpochTaken { .. })
        )
    }
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
    /// This planner took `run` over at fencing token `epoch`; `previous` held it before.
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
    /// This planner's etcd lease (absent for a single daemon, which needs none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lease: Option<LeaseStatus>,
}

/// A run this planner holds: its token and the lease it holds it on (`None`: alone).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Held {
    token: u64,
    lease: Option<i64>,
}

/// A run in [`Fleet::take`]: listed in the fleet's `taking` set from before its owner key is
/// created until it is held, or until the take fails (dropped on every path out).
struct Taking<'a> {
    set: &'a Mutex<HashSet<String>>,
    run: String,
}

impl<'a> Taking<'a> {
    fn start(set: &'a Mutex<HashSet<String>>, run: &str) -> Self {
        set.lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(run.to_string());
        Self {
            set,
            run: run.to_string(),
        }
    }
}

impl Drop for Taking<'_> {
    fn drop(&mut self) {
        self.set
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(&self.run);
    }
}

/// The owner keys etcd lists for this planner (`owned`: run and token) that it neither holds
/// at that token nor is taking over right now: left behind by a release that failed.
fn strays(
    owned: Vec<(String, u64)>,
    held: &HashMap<String, Held>,
    taking: &HashSet<String>,
) -> Vec<(String, u64)> {
    owned
        .into_iter()
        .filter(|(run, token)| {
            !taking.contains(run) && held.get(run).is_none_or(|h| h.token != *token)
        })
        .collect()
}

/// This planner's membership of the fleet.
pub struct Fleet {
    me: String,
    pins: Pins,
    keys: Keys,
    /// The fleet's ownership authority; `None` for a single daemon.
    etcd: Option<Arc<EtcdOwners>>,
    view: Mutex<View>,
    /// The runs this planner holds.
    held: Mutex<HashMap<String, Held>>,
    /// The runs this planner is taking over now: their owner key exists in etcd from the
    /// moment its create succeeds, before the token is on disk and the run in `held`, and
    /// [`Fleet::release_strays`] must not take it for one a failed release left behind.
    taking: Mutex<HashSet<String>>,
    events: Mutex<VecDeque<FleetEvent>>,
    /// Runs whose owner found itself fenced; the service steps down from them.
    fenced: Mutex<Vec<String>>,
    /// Wakes the service's steward whenever something may have changed: any number of
    /// token events between two looks coalesce into one.
    changed: Arc<Notify>,
    session: zenoh::Session,
    /// This planner's liveliness token, declared while it may take runs (see
    /// [`Fleet::show_presence`]).
    presence: tokio::sync::Mutex<Option<zenoh::liveliness::LivelinessToken>>,
}

impl Fleet {
    /// A single daemon: owns every run in its data directory, watches no one.
    pub fn alone(session: zenoh::Session, keys: Keys, me: String) -> Arc<Self> {
        Arc::new(Self::new(session, keys, me, Pins::default(), None))
    }

    fn new(
        session: zenoh::Session,
        keys: Keys,
        me: String,
        pins: Pins,
        etcd: Option<Arc<EtcdOwners>>,
    ) -> Self {
        let mut view = View::default();
        view.planner_joined(&me);
        view.set_pins(&me, pins.clone());
        Self {
            me,
            pins,
            keys,
            etcd,
            view: Mutex::new(view),
            held: Mutex::new(HashMap::new()),
            taking: Mutex::new(HashSet::new()),
            events: Mutex::new(VecDeque::new()),
            fenced: Mutex::new(Vec::new()),
            changed: Arc::new(Notify::new()),
            session,
            presence: tokio::sync::Mutex::new(None),
        }
    }

    /// Joins a fleet: connects to etcd and holds a lease there (kept alive on a task of its
    /// own), reads the owner keys now and every `OWNERS_REFRESH`, serves this planner's pins
    /// and watches the planner tokens, reading the ones already declared. Waits up to a
    /// lease's margin for the first lease, so a planner that starts with etcd up resumes its
    /// share at once. (The planner's own liveliness token is the service's to declare.)
    pub async fn join(
        session: zenoh::Session,
        keys: Keys,
        me: String,
        config: &FleetConfig,
    ) -> Result<Arc<Self>, FleetError> {
        let timing = LeaseTiming::new(config.lease_ttl_seconds);
        let etcd = EtcdOwners::connect(&config.etcd, keys.prefix(), &me, timing).await?;
        let fleet = Arc::new(Self::new(
            session.clone(),
            keys,
            me,
            config.pins(),
            Some(etcd.clone()),
        ));
        let runtime = tokio::runtime::Handle::current();
        let wake = fleet.changed.clone();
        runtime.spawn(etcd.clone().keep_alive(move || wake.notify_one()));
        let (owners, wake) = (etcd.clone(), fleet.changed.clone());
        runtime.spawn(async move {
            loop {
                if let Ok(true) = owners.refresh().await {
                    wake.notify_one();
                }
                tokio::time::sleep(OWNERS_REFRESH).await;
            }
        });
        let started = tokio::time::Instant::now();
        while !etcd.lease_valid() && started.elapsed() < timing.margin {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        if !etcd.lease_valid() {
            tracing::warn!("no etcd lease yet: this planner takes no run until it gets one");
        }
        // The owners as of now, before the service's first look at the stored runs.
        let _ = etcd.refresh().await;
        let profile = serde_json::to_vec(&fleet.pins).expect("pins serialise");
        session
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
        let key = fleet.keys.all_planners_alive();
        let weak = Arc::downgrade(&fleet);
        let (handle, watcher) = (runtime.clone(), session.clone());
        session
            .liveliness()
            .declare_subscriber(&key)
            .callback(move |sample| {
                if let Some(fleet) = weak.upgrade() {
                    fleet.token(&sample, &watcher, &handle);
                }
            })
            .background()
            .await
            .map_err(zenoh_err("watching liveliness"))?;
        let replies = session
            .liveliness()
            .get(&key)
            .timeout(PINS_TIMEOUT)
            .await
            .map_err(zenoh_err("reading liveliness"))?;
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                fleet.token(sample, &session, &runtime);
            }
        }
        Ok(fleet)
    }

    pub fn me(&self) -> &str {
        &self.me
    }

    /// Whether this planner is one of a fleet (etcd decides), not a single daemon.
    pub fn in_fleet(&self) -> bool {
        self.etcd.is_some()
    }

    /// Declares this planner's liveliness token while it may take runs, and withdraws it
    /// while it may not: a fleet planner holds its token only while its etcd lease is valid.
    /// The token is what the other planners prefer free runs on (rendezvous hashing over the
    /// live planners): a planner cut off from etcd that kept it would stay the preferred
    /// planner of its own runs once etcd expired its lease, and they would wait a whole
    /// [`FREE_GRACE`] for another planner. Agents watching their owner's token (sim-bridge)
    /// attach again at once when it goes. A single daemon always shows it. Called at start
    /// (once the stored runs are resumed) and by the service's steward at every look.
    pub async fn show_presence(&self) {
        let wanted = self.etcd.as_ref().is_none_or(|etcd| etcd.lease_valid());
        let mut presence = self.presence.lock().await;
        if wanted == presence.is_some() {
            return;
        }
        if !wanted {
            tracing::warn!(
                "no valid etcd lease: planner token withdrawn, so no run is preferred here"
            );
            *presence = None;
            return;
        }
        match self
            .session
            .liveliness()
            .declare_token(self.keys.planner_alive(&self.me))
            .await
        {
            Ok(token) => {
                if self.etcd.is_some() {
                    tracing::info!("etcd lease held: planner token declared");
                }
                *presence = Some(token);
            }
            Err(e) => tracing::error!(error = %e, "cannot declare the planner token"),
        }
    }

    /// What wakes the service's steward.
    pub fn changes(&self) -> Arc<Notify> {
        self.changed.clone()
    }

    /// Applies a planner token's appearance or departure to the view. Bounded work: the view
    /// keeps valid names only, at most [`view::MAX_PLANNERS`]; a token that changes nothing
    /// costs nothing; the steward's wake-ups coalesce.
    fn token(
        self: &Arc<Self>,
        sample: &Sample,
        session: &zenoh::Session,
        runtime: &tokio::runtime::Handle,
    ) {
        let key = sample.key_expr().as_str();
        let put = sample.kind() == SampleKind::Put;
        let Some(planner) = self.keys.parse_planner_alive(key) else {
            return;
        };
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
            runtime.spawn(self.clone().fetch_pins(session.clone(), planner));
        } else {
            tracing::info!(%planner, "planner left the fleet");
            self.event(FleetEventKind::PlannerLeft { planner });
        }
        self.changed.notify_one();
    }

    /// Asks `planner` for its pins; until they come it counts as allowing every run.
    async fn fetch_pins(self: Arc<Self>, session: zenoh::Session, planner: String) {
        let key = self.keys.planner_fleet(&planner);
        let pins = async {
            let replies = session
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
                self.changed.notify_one();
            }
            Err(reason) => {
                tracing::warn!(%planner, %reason, "cannot read a planner's pins; it counts as serving every run");
            }
        }
    }

    fn lock_view(&self) -> std::sync::MutexGuard<'_, View> {
        self.view.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn lock_held(&self) -> std::sync::MutexGuard<'_, HashMap<String, Held>> {
        self.held.lock().unwrap_or_else(PoisonError::into_inner)
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

    /// Who owns `run` (etcd's owner key), or, if nobody does, which planner it is preferred on.
    pub fn owner(&self, run: &str) -> Owner {
        let Some(etcd) = &self.etcd else {
            return Owner::Placed {
                planner: self.me.clone(),
            };
        };
        match etcd.owner(run) {
            Some(key) => Owner::Holder {
                planner: key.planner,
                epoch: key.token,
            },
            None => self.lock_view().placed(run),
        }
    }

    /// Whether this planner should serve `run`: it holds it, or nobody does and it is
    /// preferred here (and this planner holds a valid lease, so it could take it). A single
    /// daemon serves every run.
    pub fn is_mine(&self, run: &str) -> bool {
        let Some(etcd) = &self.etcd else {
            return true;
        };
        if let Some(held) = self.lock_held().get(run) {
            return etcd.valid_lease() == held.lease;
        }
        etcd.lease_valid()
            && etcd.owner(run).is_none()
            && self.lock_view().placed(run).planner() == Some(self.me.as_str())
    }

    /// Whether this planner may take `run` now although it is not preferred here: nobody has
    /// held it for `free_for` (its preferred planner does not take it).
    pub fn may_take_unpreferred(&self, run: &str, free_for: Duration) -> bool {
        let Some(etcd) = &self.etcd else {
            return true;
        };
        free_for >= FREE_GRACE && etcd.lease_valid() && etcd.owner(run).is_none()
    }

    /// Whether etcd currently names an owner for `run` (always `false` for a single daemon).
    pub fn has_owner_key(&self, run: &str) -> bool {
        self.etcd.as_ref().is_some_and(|e| e.owner(run).is_some())
    }

    /// Whether this planner may acknowledge a step of `run` it holds at `token` now: always
    /// for a single daemon; in a fleet, only while its lease is valid by its own clock (it
    /// ends a margin before etcd could expire it) and it still holds the run at that token.
    pub fn may_acknowledge(&self, run: &str, token: u64) -> bool {
        let Some(etcd) = &self.etcd else {
            return true;
        };
        let held = self.lock_held().get(run).copied();
        held.is_some_and(|h| h.token == token && h.lease.is_some() && etcd.valid_lease() == h.lease)
    }

    /// Takes `run` over and returns its fencing token. A single daemon claims the epoch after
    /// the newest in `dir`; a fleet planner creates the run's owner key in etcd (only if
    /// absent, so only if nobody holds the run), then records the token in `dir`, where it
    /// is the floor for later tokens and the on-disk fence that `Run::check_owner` reads.
    ///
    /// # Errors
    /// [`FleetError::is_contended`] when another planner holds the run; others when etcd or
    /// the disk fail.
    pub async fn take(&self, run: &str, dir: &RunDir) -> Result<u64, FleetError> {
        let mut taking = None;
        let on_disk = dir.clone();
        let seen = blocking(move || on_disk.current_epoch()).await?;
        let previous = dir.epoch_holder(seen);
        let (token, lease) = match &self.etcd {
            None => {
                let (on_disk, me) = (dir.clone(), self.me.clone());
                let epoch = blocking(move || on_disk.claim_epoch_after(seen, &me)).await?;
                (epoch, None)
            }
            Some(etcd) => {
                let lease = etcd.valid_lease().ok_or(EtcdError::NoLease)?;
                taking = Some(Taking::start(&self.taking, run));
                let token = etcd.take(run, seen).await?;
                let (on_disk, me) = (dir.clone(), self.me.clone());
                if let Err(e) = blocking(move || on_disk.record_token(token, &me)).await {
                    if let Err(released) = etcd.release(run, token).await {
                        tracing::warn!(%run, error = %released, "cannot release the owner key; it goes with the lease");
                    }
                    return Err(e);
                }
                (token, Some(lease))
            }
        };
        {
            let mut held = self.lock_held();
            held.insert(run.to_string(), Held { token, lease });
            drop(taking);
        }
        tracing::info!(%run, token, previous = ?previous, "took the run");
        self.event(FleetEventKind::Took {
            run: run.to_string(),
            epoch: token,
            previous,
        });
        Ok(token)
    }

    /// Gives `run` up, saying why: in a fleet its owner key is deleted (if it is still the
    /// one this planner created), so another planner may take it at once.
    pub fn step_down(&self, run: &str, reason: String) {
        let held = self.lock_held().remove(run);
        let Some(held) = held else { return };
        tracing::warn!(%run, token = held.token, %reason, "stepped down");
        self.event(FleetEventKind::SteppedDown {
            run: run.to_string(),
            epoch: held.token,
            reason,
        });
        if let Some(etcd) = &self.etcd {
            let (etcd, run) = (etcd.clone(), run.to_string());
            tokio::runtime::Handle::current().spawn(async move {
                if let Err(e) = etcd.release(&run, held.token).await {
                    tracing::warn!(%run, error = %e, "cannot release the owner key; released later, or with the lease");
                }
            });
        }
    }

    /// The runs this planner holds but may no longer serve, with the reason: its lease is no
    /// longer valid (it could not renew in time), or etcd names another owner.
    pub fn lost_runs(&self) -> Vec<(String, String)> {
        let Some(etcd) = &self.etcd else {
            return Vec::new();
        };
        let lease = etcd.valid_lease();
        self.lock_held()
            .iter()
            .filter_map(|(run, held)| {
                if held.lease != lease {
                    return Some((
                        run.clone(),
                        "this planner's etcd lease could not be renewed in time".to_string(),
                    ));
                }
                match etcd.owner(run) {
                    Some(key) if key.token != held.token => Some((
                        run.clone(),
                        format!("{} holds it at token {}", key.planner, key.token),
                    )),
                    _ => None,
                }
            })
            .collect()
    }

    /// Owner keys etcd lists for this planner on its current lease that it does not hold (a
    /// release that failed while etcd was unreachable): released now, so no run stays owned
    /// by a planner that does not serve it.
    pub async fn release_strays(&self) {
        let Some(etcd) = &self.etcd else { return };
        let Some(lease) = etcd.valid_lease() else {
            return;
        };
        let strays = {
            // `held` before `taking`: a take moves its run from one to the other only with
            // `held` locked, so no run is seen in neither while it is being taken.
            let held = self.lock_held();
            let taking = self.taking.lock().unwrap_or_else(PoisonError::into_inner);
            strays(etcd.owned_by(&self.me, lease), &held, &taking)
        };
        for (run, token) in strays {
            tracing::info!(%run, token, "releasing an owner key this planner does not serve");
            if let Err(e) = etcd.release(&run, token).await {
                tracing::warn!(%run, error = %e, "cannot release a stray owner key");
            }
        }
    }

    /// At shutdown: the planner token is withdrawn and the lease revoked, so every run this
    /// planner held is free at once.
    pub async fn leave(&self) {
        *self.presence.lock().await = None;
        if let Some(etcd) = &self.etcd {
            etcd.revoke().await;
        }
    }

    /// An owner found on disk that it lost `run`: the service steps down at its next turn.
    pub fn report_fenced(&self, run: &str) {
        self.fenced
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(run.to_string());
        self.changed.notify_one();
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
            lease: self.etcd.as_ref().map(|e| e.status()),
        }
    }
}

/// Runs blocking disk work on the blocking pool.
async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T, PersistError> + Send + 'static,
) -> Result<T, FleetError> {
    match tokio::task::spawn_blocking(work).await {
        Ok(result) => Ok(result?),
        Err(e) => Err(FleetError::Task(e.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn held(entries: &[(&str, u64)]) -> HashMap<String, Held> {
        entries
            .iter()
            .map(|(run, token)| {
                let held = Held {
                    token: *token,
                    lease: Some(7),
                };
                (run.to_string(), held)
            })
            .collect()
    }

    fn owned(entries: &[(&str, u64)]) -> Vec<(String, u64)> {
        entries.iter().map(|(r, t)| (r.to_string(), *t)).collect()
    }

    #[test]
    fn a_key_left_by_a_failed_release_is_a_stray() {
        let strays = strays(
            owned(&[("run-0", 4), ("run-1", 5)]),
            &held(&[("run-0", 4)]),
            &HashSet::new(),
        );
        assert_eq!(strays, owned(&[("run-1", 5)]));
    }

    #[test]
    fn a_key_at_an_older_token_than_the_one_held_is_a_stray() {
        let strays = strays(
            owned(&[("run-0", 3)]),
            &held(&[("run-0", 4)]),
            &HashSet::new(),
        );
        assert_eq!(strays, owned(&[("run-0", 3)]));
    }

    /// The owner key of a run being taken exists before the run is held: releasing it then
    /// would let another planner take the run from under the one that is opening it.
    #[test]
    fn a_run_being_taken_is_no_stray() {
        let taking = HashSet::from(["run-2".to_string()]);
        let strays = strays(owned(&[("run-2", 4)]), &held(&[]), &taking);
        assert!(strays.is_empty(), "{strays:?}");
    }

    #[test]
    fn taking_lists_the_run_until_dropped() {
        let set = Mutex::new(HashSet::new());
        {
            let _taking = Taking::start(&set, "run-2");
            assert!(set.lock().unwrap().contains("run-2"));
        }
        assert!(set.lock().unwrap().is_empty());
    }
}
