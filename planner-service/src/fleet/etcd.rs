//! Run ownership in etcd: the only authority on who owns a run in a fleet.
//!
//! ```text
//! {prefix}/owners/{run}      value: the owner's planner id, attached to the owner's lease;
//!                            its create revision is the run's fencing token
//! {prefix}/revision-floor    written only to raise etcd's revision above a token already on
//!                            disk (a run stored by a single daemon, or an etcd rebuilt empty)
//! ```
//!
//! Each planner holds one etcd lease and keeps it alive. A run's owner key is created in a
//! transaction only when it is absent, attached to the creator's lease, so it exists exactly
//! as long as its owner's lease does and no other planner can create it meanwhile. Its create
//! revision grows with every new owner (etcd's revision never goes back), which makes it the
//! fencing token written into every replay record, `Action` and `AttachAccepted`.
//!
//! **Stopping before the lease can expire.** etcd expires a lease `ttl` after the last
//! keep-alive it received, by its own clock. This planner takes the instant it *sent* the last
//! answered keep-alive (necessarily no later than etcd received it) and counts the lease valid
//! until `ttl - margin` after that, by its own monotonic clock: past that instant it
//! acknowledges nothing, so no acknowledgement is ever sent once another planner could own
//! the run. Clock *rates* must agree to within `margin / ttl` (20 %); no clocks are compared.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use etcd_client::{
    Client, Compare, CompareOp, ConnectOptions, GetOptions, PutOptions, Txn, TxnOp, TxnOpResponse,
};

/// Time allowed to one etcd request (a takeover, a read of the owners, a keep-alive).
const REQUEST_TIMEOUT: Duration = Duration::from_secs(2);

/// Most puts made to lift etcd's revision above a fencing token already on disk.
const MAX_REVISION_LIFT: i64 = 100_000;

/// Failures to reach or use etcd.
#[derive(Debug, thiserror::Error)]
pub enum EtcdError {
    #[error("etcd: {0}")]
    Client(#[from] etcd_client::Error),
    #[error("etcd did not answer within {0:?}")]
    Timeout(Duration),
    #[error("this planner holds no valid etcd lease (etcd unreachable, or the lease expired)")]
    NoLease,
    #[error("run `{run}` is owned by {holder} (fencing token {token})")]
    Owned {
        run: String,
        holder: String,
        token: u64,
    },
    #[error(
        "etcd's revision {revision} is {gap} below the run's newest fencing token on disk: more than {MAX_REVISION_LIFT} to lift"
    )]
    RevisionTooLow { revision: i64, gap: i64 },
    #[error("etcd answered without a {0}")]
    Malformed(&'static str),
}

async fn timed<T>(
    what: impl std::future::Future<Output = Result<T, etcd_client::Error>>,
) -> Result<T, EtcdError> {
    match tokio::time::timeout(REQUEST_TIMEOUT, what).await {
        Ok(result) => Ok(result?),
        Err(_) => Err(EtcdError::Timeout(REQUEST_TIMEOUT)),
    }
}

/// How long leases live, and how much of it this planner leaves unused.
#[derive(Clone, Copy, Debug)]
pub struct LeaseTiming {
    pub ttl: Duration,
    pub margin: Duration,
}

impl LeaseTiming {
    /// A lease of `ttl_seconds`, with a margin of a fifth of it (at least 1 s).
    pub fn new(ttl_seconds: u64) -> Self {
        let ttl = Duration::from_secs(ttl_seconds);
        Self {
            ttl,
            margin: (ttl / 5).max(Duration::from_secs(1)),
        }
    }

    /// How often the lease is renewed: three tries before the margin is reached.
    fn renew_every(&self) -> Duration {
        (self.ttl - self.margin) / 4
    }
}

/// The lease this planner holds.
#[derive(Debug, Default)]
struct LeaseState {
    /// etcd's id of the lease; `None` before one was granted or after it expired.
    id: Option<i64>,
    /// Until when this planner may act on its ownerships (by its own clock).
    valid_until: Option<Instant>,
}

/// The owner of a run, as etcd last said.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OwnerKey {
    pub planner: String,
    pub token: u64,
    pub lease: i64,
}

/// A planner's connection to etcd: its lease and the owners it last read.
pub struct EtcdOwners {
    client: Client,
    me: String,
    owners_prefix: String,
    floor_key: String,
    timing: LeaseTiming,
    lease: Mutex<LeaseState>,
    /// Every run's owner key, as of the last successful read.
    owners: Mutex<BTreeMap<String, OwnerKey>>,
    /// Whether the last request to etcd got an answer.
    reachable: AtomicBool,
    /// Renewals and reads that failed (shown by `status` and the metrics).
    failures: AtomicU64,
}

impl std::fmt::Debug for EtcdOwners {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EtcdOwners")
            .field("me", &self.me)
            .field("owners_prefix", &self.owners_prefix)
            .finish_non_exhaustive()
    }
}

/// What `status` shows of this planner's etcd lease.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct LeaseStatus {
    /// etcd's id of the lease, if one is held.
    pub lease_id: Option<i64>,
    /// Seconds this planner may still acknowledge without a renewal (0: it acknowledges nothing).
    pub valid_for_seconds: f64,
    pub ttl_seconds: f64,
    pub reachable: bool,
    /// Renewals and reads of the owners that failed since the start.
    pub failures: u64,
}

impl EtcdOwners {
    /// A client of the etcd cluster at `endpoints` (connections are made on first use, so
    /// this succeeds with etcd down: such a planner simply takes nothing until it is up).
    pub async fn connect(
        endpoints: &[String],
        prefix: &str,
        me: &str,
        timing: LeaseTiming,
    ) -> Result<Arc<Self>, EtcdError> {
        let options = ConnectOptions::new()
            .with_connect_timeout(REQUEST_TIMEOUT)
            .with_timeout(REQUEST_TIMEOUT)
            .with_keep_alive(Duration::from_secs(1), REQUEST_TIMEOUT);
        let client = Client::connect(endpoints, Some(options)).await?;
        Ok(Arc::new(Self {
            client,
            me: me.to_string(),
            owners_prefix: format!("{prefix}/owners/"),
            floor_key: format!("{prefix}/revision-floor"),
            timing,
            lease: Mutex::new(LeaseState::default()),
            owners: Mutex::new(BTreeMap::new()),
            reachable: AtomicBool::new(false),
            failures: AtomicU64::new(0),
        }))
    }

    fn lock_lease(&self) -> std::sync::MutexGuard<'_, LeaseState> {
        self.lease.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn lock_owners(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, OwnerKey>> {
        self.owners.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn owner_key(&self, run: &str) -> String {
        format!("{}{run}", self.owners_prefix)
    }

    /// The lease's id while it is valid by this planner's clock.
    pub fn valid_lease(&self) -> Option<i64> {
        let lease = self.lock_lease();
        match (lease.id, lease.valid_until) {
            (Some(id), Some(until)) if Instant::now() < until => Some(id),
            _ => None,
        }
    }

    /// Whether this planner may acknowledge now: its lease is valid by its own clock.
    pub fn lease_valid(&self) -> bool {
        self.valid_lease().is_some()
    }

    pub fn timing(&self) -> LeaseTiming {
        self.timing
    }

    fn failed(&self, what: &str, e: &EtcdError) {
        self.reachable.store(false, Ordering::Relaxed);
        self.failures.fetch_add(1, Ordering::Relaxed);
        tracing::warn!(error = %e, "etcd: {what} failed");
    }

    /// Keeps this planner's lease alive for as long as the planner runs, granting a new one
    /// when it expired; calls `changed` whenever the lease is lost or granted.
    pub async fn keep_alive(self: Arc<Self>, changed: impl Fn()) {
        let mut backoff = Duration::from_millis(100);
        loop {
            match self.clone().hold_lease(&changed).await {
                Ok(()) => backoff = Duration::from_millis(100),
                Err(e) => {
                    self.failed("keeping the lease alive", &e);
                    // Past its validity this planner has stepped down from everything held on
                    // the lease: renewing it later would keep those owner keys alive for runs
                    // nobody serves. It is forgotten (etcd expires it) and a new one granted.
                    let forgotten = {
                        let mut lease = self.lock_lease();
                        if lease
                            .valid_until
                            .is_none_or(|until| Instant::now() >= until)
                        {
                            lease.id.take()
                        } else {
                            None
                        }
                    };
                    if let Some(id) = forgotten {
                        tracing::error!(
                            lease = id,
                            "etcd lease not renewed in time: this planner owns nothing until it gets a new one"
                        );
                        changed();
                    }
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(self.timing.renew_every());
                }
            }
        }
    }

    /// Grants a lease if none is held, then renews it until renewing fails (an error) or etcd
    /// says it expired (`Ok`: a new one is granted next).
    async fn hold_lease(self: Arc<Self>, changed: &impl Fn()) -> Result<(), EtcdError> {
        let mut client = self.client.clone();
        let held = self.lock_lease().id;
        let id = match held {
            Some(id) => id,
            None => {
                let sent = Instant::now();
                let granted =
                    timed(client.lease_grant(self.timing.ttl.as_secs() as i64, None)).await?;
                let mut lease = self.lock_lease();
                lease.id = Some(granted.id());
                lease.valid_until = Some(sent + self.timing.ttl - self.timing.margin);
                drop(lease);
                self.reachable.store(true, Ordering::Relaxed);
                tracing::info!(
                    lease = granted.id(),
                    ttl_s = self.timing.ttl.as_secs(),
                    "etcd lease granted"
                );
                changed();
                granted.id()
            }
        };
        let (mut keeper, mut answers) = timed(client.lease_keep_alive(id)).await?;
        loop {
            let sent = Instant::now();
            timed(keeper.keep_alive()).await?;
            let answer = match tokio::time::timeout(REQUEST_TIMEOUT, answers.message()).await {
                Ok(answer) => answer?,
                Err(_) => return Err(EtcdError::Timeout(REQUEST_TIMEOUT)),
            };
            let Some(answer) = answer else {
                return Err(EtcdError::Malformed("keep-alive answer"));
            };
            self.reachable.store(true, Ordering::Relaxed);
            if answer.ttl() <= 0 {
                // Expired: everything attached to it (this planner's owner keys) is gone.
                let mut lease = self.lock_lease();
                lease.id = None;
                lease.valid_until = None;
                drop(lease);
                tracing::error!(
                    lease = id,
                    "etcd lease expired; this planner owns nothing now"
                );
                changed();
                return Ok(());
            }
            self.lock_lease().valid_until = Some(sent + self.timing.ttl - self.timing.margin);
            tokio::time::sleep(self.timing.renew_every()).await;
        }
    }

    /// Reads every run's owner key; returns whether anything changed since the last read.
    pub async fn refresh(&self) -> Result<bool, EtcdError> {
        let mut client = self.client.clone();
        let read = timed(client.get(
            self.owners_prefix.as_str(),
            Some(GetOptions::new().with_prefix()),
        ))
        .await;
        let read = match read {
            Ok(read) => read,
            Err(e) => {
                self.failed("reading the owners", &e);
                return Err(e);
            }
        };
        self.reachable.store(true, Ordering::Relaxed);
        let mut owners = BTreeMap::new();
        for kv in read.kvs() {
            let (Ok(key), Ok(planner)) = (kv.key_str(), kv.value_str()) else {
                continue;
            };
            let Some(run) = key.strip_prefix(&self.owners_prefix) else {
                continue;
            };
            owners.insert(
                run.to_string(),
                OwnerKey {
                    planner: planner.to_string(),
                    token: kv.create_revision() as u64,
                    lease: kv.lease(),
                },
            );
        }
        let mut known = self.lock_owners();
        let changed = *known != owners;
        *known = owners;
        Ok(changed)
    }

    /// The runs etcd last listed as owned by `planner` on `lease`, with their tokens.
    pub fn owned_by(&self, planner: &str, lease: i64) -> Vec<(String, u64)> {
        self.lock_owners()
            .iter()
            .filter(|(_, key)| key.planner == planner && key.lease == lease)
            .map(|(run, key)| (run.clone(), key.token))
            .collect()
    }

    /// The owner of `run` as etcd last said.
    pub fn owner(&self, run: &str) -> Option<OwnerKey> {
        self.lock_owners().get(run).cloned()
    }

    /// Takes `run`: creates its owner key on this planner's lease if it is absent. Returns the
    /// fencing token (the key's create revision), above `floor` (the newest token the run's
    /// directory records). A key this planner already holds on its current lease is kept and
    /// its token returned.
    ///
    /// # Errors
    /// [`EtcdError::Owned`] when another planner holds the run; [`EtcdError::NoLease`] without
    /// a valid lease; others when etcd cannot be reached.
    pub async fn take(&self, run: &str, floor: u64) -> Result<u64, EtcdError> {
        let lease = self.valid_lease().ok_or(EtcdError::NoLease)?;
        let key = self.owner_key(run);
        let mut client = self.client.clone();
        self.lift_revision_above(&mut client, floor).await?;
        let txn = Txn::new()
            .when([Compare::create_revision(key.as_str(), CompareOp::Equal, 0)])
            .and_then([TxnOp::put(
                key.as_str(),
                self.me.as_str(),
                Some(PutOptions::new().with_lease(lease)),
            )])
            .or_else([TxnOp::get(key.as_str(), None)]);
        let answer = timed(client.txn(txn)).await?;
        self.reachable.store(true, Ordering::Relaxed);
        let revision = answer
            .header()
            .ok_or(EtcdError::Malformed("header"))?
            .revision();
        let owner = if answer.succeeded() {
            OwnerKey {
                planner: self.me.clone(),
                token: revision as u64,
                lease,
            }
        } else {
            let held = answer.op_responses().into_iter().find_map(|op| match op {
                TxnOpResponse::Get(get) => get.kvs().first().map(|kv| OwnerKey {
                    planner: kv.value_str().unwrap_or("?").to_string(),
                    token: kv.create_revision() as u64,
                    lease: kv.lease(),
                }),
                _ => None,
            });
            // Deleted between the compare and the get cannot happen inside one txn.
            held.ok_or(EtcdError::Malformed("owner key"))?
        };
        self.lock_owners().insert(run.to_string(), owner.clone());
        if owner.planner == self.me && owner.lease == lease {
            Ok(owner.token)
        } else {
            Err(EtcdError::Owned {
                run: run.to_string(),
                holder: owner.planner,
                token: owner.token,
            })
        }
    }

    /// Makes etcd's next revision exceed `floor`: a run's data may carry tokens from before
    /// this etcd (a single daemon's epochs, or an etcd cluster rebuilt empty), and a new
    /// owner's token must be newer than every one of them.
    async fn lift_revision_above(&self, client: &mut Client, floor: u64) -> Result<(), EtcdError> {
        let floor = floor.min(i64::MAX as u64) as i64;
        let probe = timed(client.get(self.floor_key.as_str(), None)).await?;
        let mut revision = probe
            .header()
            .ok_or(EtcdError::Malformed("header"))?
            .revision();
        if revision + 1 > floor {
            return Ok(());
        }
        let gap = floor - revision;
        if gap > MAX_REVISION_LIFT {
            return Err(EtcdError::RevisionTooLow { revision, gap });
        }
        tracing::warn!(
            revision,
            floor,
            "lifting etcd's revision above a fencing token on disk"
        );
        while revision < floor {
            let put = timed(client.put(self.floor_key.as_str(), self.me.as_str(), None)).await?;
            revision = put
                .header()
                .ok_or(EtcdError::Malformed("header"))?
                .revision();
        }
        Ok(())
    }

    /// Gives `run` up: deletes its owner key if it is still the one created at `token`.
    pub async fn release(&self, run: &str, token: u64) -> Result<(), EtcdError> {
        let key = self.owner_key(run);
        let txn = Txn::new()
            .when([Compare::create_revision(
                key.as_str(),
                CompareOp::Equal,
                token as i64,
            )])
            .and_then([TxnOp::delete(key.as_str(), None)]);
        let mut client = self.client.clone();
        timed(client.txn(txn)).await?;
        let mut owners = self.lock_owners();
        if owners.get(run).is_some_and(|o| o.token == token) {
            owners.remove(run);
        }
        Ok(())
    }

    /// Revokes the lease (every owner key on it goes at once), at shutdown.
    pub async fn revoke(&self) {
        let id = {
            let mut lease = self.lock_lease();
            lease.valid_until = None;
            lease.id.take()
        };
        if let Some(id) = id {
            let mut client = self.client.clone();
            match timed(client.lease_revoke(id)).await {
                Ok(_) => tracing::info!(lease = id, "etcd lease revoked; the runs are free"),
                Err(e) => {
                    tracing::warn!(lease = id, error = %e, "cannot revoke the etcd lease; it expires by itself")
                }
            }
        }
    }

    pub fn status(&self) -> LeaseStatus {
        let lease = self.lock_lease();
        let now = Instant::now();
        LeaseStatus {
            lease_id: lease.id,
            valid_for_seconds: lease.valid_until.map_or(0.0, |until| {
                until.saturating_duration_since(now).as_secs_f64()
            }),
            ttl_seconds: self.timing.ttl.as_secs_f64(),
            reachable: self.reachable.load(Ordering::Relaxed),
            failures: self.failures.load(Ordering::Relaxed),
        }
    }
}
