//! A run's replay buffer: every transition any of its agents produced, in memory for training
//! and in an append-only log on disk so that a restarted daemon resumes with all of it.

mod log;
pub mod segments;

#[cfg(test)]
pub(crate) use log::tests as log_tests;
pub use log::{
    ActionOrigin, ClaimRecord, EpisodeEndRecord, HeaderRecord, LogError, LogFile, LogSyncer,
    Record, Recovered, ReplayLog, Rewrite, RewritePlan, SegmentRead, TermRecord, TransitionRecord,
};

use crate::data::Transitions;
use proto::{EpisodeEnd, Task};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::ops::DerefMut;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Whether this planner still owns the run, asked just before it removes a superseded replay
/// segment (a fleet: its lease is valid by its own clock and it holds the run at its token).
#[derive(Clone)]
pub struct OwnerCheck(pub Arc<dyn Fn() -> bool + Send + Sync>);

impl OwnerCheck {
    /// A planner alone owns its runs for as long as it has them open.
    pub fn alone() -> Self {
        Self(Arc::new(|| true))
    }

    pub fn holds(&self) -> bool {
        (self.0)()
    }
}

impl std::fmt::Debug for OwnerCheck {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("OwnerCheck")
    }
}

/// The ownership term a buffer is opened for.
pub struct Term<'a> {
    /// The fencing token.
    pub token: u64,
    /// The planner holding it.
    pub planner: &'a str,
    /// Asked before a superseded segment is removed.
    pub still_owner: OwnerCheck,
}

/// A finished episode, as stored.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeSummary {
    pub agent: String,
    pub episode: u32,
    pub steps: u32,
    pub episode_return: f32,
    pub end: EpisodeEnd,
}

/// Failures of the replay buffer.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Log(#[from] LogError),
    #[error("replay log {path} holds task {found}, this run is {expected}")]
    TaskMismatch {
        path: String,
        found: String,
        expected: String,
    },
    #[error("replay log {path} does not start with a header record")]
    MissingHeader { path: String },
    #[error("a replay record does not fit the run's dimensions: {record}")]
    Dimension { record: String },
}

/// Transitions in memory, mirrored to an optional log file.
///
/// With a capacity (see [`ReplayBuffer::set_capacity`]), the transitions of the oldest
/// finished episodes are evicted whole once the buffer holds more than the capacity: at once
/// from memory, and from the log by [`compact_log`] once the evicted records on disk
/// outnumber the kept ones (so the log stays under about twice the capacity and each record is
/// rewritten a bounded number of times). Episode summaries are never evicted: they are small, and episode counts
/// and numbering depend on them.
#[derive(Debug)]
pub struct ReplayBuffer {
    task: &'static Task,
    transitions: Transitions,
    /// Which action each transition holds, in the order of `transitions`.
    origins: Vec<ActionOrigin>,
    /// The episode each transition belongs to: (index into `agents`, episode number).
    owners: Vec<(u32, u32)>,
    agents: Vec<String>,
    episodes: Vec<EpisodeSummary>,
    /// The writer of this term's segment (see [`segments`]), `None` in memory only.
    log: Option<ReplayLog>,
    /// The run's directory, where its segments are (`None` in memory only).
    root: Option<PathBuf>,
    /// The earlier segments this term's data continues from, each with its length that counts.
    earlier: Vec<(PathBuf, u64)>,
    /// The fencing token of this term (its segments are named by it).
    token: u64,
    /// The planner holding this term (named in the segments it writes).
    planner: String,
    /// Asked before removing superseded segments (see [`OwnerCheck`]).
    still_owner: OwnerCheck,
    /// Episodes found open when the run was read, as their interrupted ends (recorded once
    /// the buffer has its log).
    left_open: Vec<Record>,
    /// Segments a finished compaction superseded, to remove once its segment is durable.
    superseded: Vec<PathBuf>,
    /// The ownership epoch of the newest claim: what this buffer writes under, and below which
    /// records are stale.
    epoch: u64,
    /// Records of an older epoch found after a newer claim when the log was opened (written by
    /// a planner that had lost the run); skipped.
    stale_skipped: usize,
    /// Most transitions kept (`None`: all).
    capacity: Option<usize>,
    /// Episodes evicted from memory whose records may still be in the log.
    evicted: HashSet<(String, u32)>,
    /// Transitions evicted from memory whose records are still in the log.
    evicted_on_disk: usize,
    /// A compaction of the log is under way (see [`compact_log`]).
    compacting: bool,
    /// What opening the log could not read (damaged records, a damaged header, a torn tail),
    /// said in words for `status`; `None` for a clean log.
    damage: Option<String>,
}

impl From<EpisodeSummary> for Record {
    /// The episode's end record, at epoch 0 until a buffer stores it under its own (see
    /// [`ReplayBuffer::append`]).
    fn from(summary: EpisodeSummary) -> Self {
        let EpisodeSummary {
            agent,
            episode,
            steps,
            episode_return,
            end,
        } = summary;
        Record::EpisodeEnd(EpisodeEndRecord {
            epoch: 0,
            agent,
            episode,
            steps,
            episode_return,
            end,
        })
    }
}

impl ReplayBuffer {
    /// A buffer that lives in memory only (tests, benchmarks).
    pub fn in_memory(task: &'static Task) -> Self {
        Self {
            task,
            transitions: Transitions::new(task.obs_dim, task.act_dim),
            origins: Vec::new(),
            owners: Vec::new(),
            agents: Vec::new(),
            episodes: Vec::new(),
            log: None,
            root: None,
            earlier: Vec::new(),
            token: 0,
            planner: String::new(),
            still_owner: OwnerCheck::alone(),
            left_open: Vec::new(),
            superseded: Vec::new(),
            epoch: 0,
            stale_skipped: 0,
            capacity: None,
            evicted: HashSet::new(),
            evicted_on_disk: 0,
            compacting: false,
            damage: None,
        }
    }

    /// Opens the run stored in directory `root` (creating it) as its owner at fencing token
    /// `token`, held by `planner`: reads every intact record of its segments (see
    /// [`segments`]) except stale ones (an entry whose epoch is below that of a claim before
    /// it, written to a shared log by a planner that had lost the run, is skipped with a
    /// warning), then starts this term's own segment, which continues from them and records
    /// the claim. Refused with [`LogError::Fenced`] if a newer term has a segment already.
    ///
    /// Episodes the log holds transitions of but no end (the daemon stopped in their middle)
    /// are recorded as interrupted here: their transitions stay (they were acknowledged), and
    /// their agents continue with the next episode number rather than resuming a stale one.
    pub fn open(
        root: &Path,
        task: &'static Task,
        token: u64,
        planner: &str,
    ) -> Result<Self, ReplayError> {
        let term = Term {
            token,
            planner,
            still_owner: OwnerCheck::alone(),
        };
        Self::open_with(root, task, term, |file| Box::new(file))
    }

    /// As [`ReplayBuffer::open`] for `term`, writing through `wrap(file)` (tests inject a
    /// failing disk).
    pub fn open_with(
        root: &Path,
        task: &'static Task,
        term: Term<'_>,
        wrap: impl FnOnce(std::fs::File) -> Box<dyn LogFile>,
    ) -> Result<Self, ReplayError> {
        let Term {
            token,
            planner,
            still_owner,
        } = term;
        let mut view = segments::read(root)?;
        let recovered = std::mem::take(&mut view.recovered);
        let mut buffer = Self::from_records(root, recovered, &view.missing, task)?;
        let header = Record::Header(HeaderRecord {
            task: task.name().to_string(),
            obs_dim: task.obs_dim as u32,
            act_dim: task.act_dim as u32,
        });
        let opened = segments::create(root, &view, header, (token, planner), wrap)?;
        let garbage: Vec<PathBuf> = view.garbage.iter().map(|id| root.join(id.name())).collect();
        buffer.log = Some(opened.log);
        buffer.root = Some(root.to_path_buf());
        buffer.earlier = opened.earlier;
        buffer.token = token;
        buffer.planner = planner.to_string();
        buffer.still_owner = still_owner;
        buffer.epoch = buffer.epoch.max(token);
        let left_open = std::mem::take(&mut buffer.left_open);
        if !left_open.is_empty() {
            buffer.append(left_open)?;
            if let Some(syncer) = buffer.syncer() {
                syncer.sync()?;
            }
        }
        if !garbage.is_empty() {
            let still_owner = buffer.still_owner.clone();
            segments::remove(root, &garbage, &|| still_owner.holds());
        }
        Ok(buffer)
    }

    /// The run stored in directory `root` as [`ReplayBuffer::open`] would find it, writing
    /// nothing (safe beside its owner; for tools and tests). Episodes left open are recorded
    /// as interrupted in memory only.
    pub fn read(root: &Path, task: &'static Task) -> Result<Self, ReplayError> {
        let view = segments::read(root)?;
        let mut buffer = Self::from_records(root, view.recovered, &view.missing, task)?;
        let left_open = std::mem::take(&mut buffer.left_open);
        for record in &left_open {
            buffer.apply(record);
        }
        Ok(buffer)
    }

    /// A buffer holding the run's `recovered` records (no log yet), with the episodes left open
    /// in `left_open`, for the caller to record.
    fn from_records(
        root: &Path,
        recovered: Recovered,
        missing: &[String],
        task: &'static Task,
    ) -> Result<Self, ReplayError> {
        let path = root.join(segments::DIR);
        if recovered.truncated_bytes > 0 {
            tracing::warn!(path = %path.display(), bytes = recovered.truncated_bytes, "ignored a torn tail of the replay log");
        }
        if recovered.damaged_regions > 0 {
            tracing::warn!(path = %path.display(), regions = recovered.damaged_regions, bytes = recovered.damaged_bytes, "skipped damaged records in the replay log; every intact record is kept");
        }
        let mut buffer = Self::in_memory(task);
        let mut damage = Vec::new();
        if recovered.damaged_regions > 0 {
            damage.push(format!(
                "{} damaged stretch(es) of {} bytes skipped",
                recovered.damaged_regions, recovered.damaged_bytes
            ));
        }
        if recovered.truncated_bytes > 0 {
            damage.push(format!(
                "a torn tail of {} bytes ignored",
                recovered.truncated_bytes
            ));
        }
        if !missing.is_empty() {
            damage.push(format!("segments missing or short: {}", missing.join(", ")));
        }
        let mut records = recovered.records.into_iter().peekable();
        match records.peek() {
            None => {}
            Some(Record::Header(HeaderRecord { task: found, .. })) if found == task.name() => {
                records.next();
            }
            Some(Record::Header(HeaderRecord { task: found, .. })) => {
                return Err(ReplayError::TaskMismatch {
                    path: path.display().to_string(),
                    found: found.clone(),
                    expected: task.name().to_string(),
                });
            }
            // The first record is not the header, and damage was skipped: the header was
            // damaged. It only names the task, which the run's spec names too, and every
            // record's dimensions are checked against the task below: the run resumes with
            // every record that can be read, and says so.
            Some(_) if recovered.damaged_regions > 0 => {
                tracing::warn!(path = %path.display(), "the replay log's header record is damaged; resuming with every intact record");
                damage.push("its header record is damaged".into());
            }
            Some(_) => {
                return Err(ReplayError::MissingHeader {
                    path: path.display().to_string(),
                });
            }
        }
        buffer.damage = (!damage.is_empty()).then(|| format!("replay log: {}", damage.join("; ")));
        let mut open_episodes: BTreeMap<(String, u32), EpisodeSummary> = BTreeMap::new();
        for record in records {
            if record.epoch().is_some_and(|e| e < buffer.epoch) {
                buffer.stale_skipped += 1;
                continue;
            }
            if !buffer.fits(&record) {
                tracing::warn!(path = %path.display(), "skipped a replay record whose dimensions do not fit the task");
                continue;
            }
            match &record {
                Record::Transition(TransitionRecord {
                    agent,
                    episode,
                    step,
                    reward,
                    ..
                }) => {
                    let open = open_episodes
                        .entry((agent.clone(), *episode))
                        .or_insert_with(|| EpisodeSummary {
                            agent: agent.clone(),
                            episode: *episode,
                            steps: 0,
                            episode_return: 0.0,
                            end: EpisodeEnd::Interrupted,
                        });
                    open.steps = open.steps.max(step.saturating_add(1));
                    open.episode_return += reward;
                }
                Record::EpisodeEnd(EpisodeEndRecord { agent, episode, .. }) => {
                    open_episodes.remove(&(agent.clone(), *episode));
                }
                Record::Header(_) | Record::Claim(_) | Record::Term(_) => {}
            }
            buffer.apply(&record);
        }
        if buffer.stale_skipped > 0 {
            tracing::warn!(path = %path.display(), records = buffer.stale_skipped, epoch = buffer.epoch, "skipped records a planner wrote after it had lost the run");
        }
        buffer.left_open = open_episodes
            .into_values()
            .inspect(|summary| tracing::warn!(path = %path.display(), agent = %summary.agent, episode = summary.episode, steps = summary.steps, "episode left open by a stopped daemon recorded as interrupted"))
            .map(Record::from)
            .collect();
        Ok(buffer)
    }

    /// Whether a record's vectors have the task's dimensions. The log's checksums catch
    /// damage; this catches a record that is intact but cannot belong to this run.
    fn fits(&self, record: &Record) -> bool {
        match record {
            Record::Transition(TransitionRecord {
                obs, act, next_obs, ..
            }) => {
                obs.len() == self.task.obs_dim
                    && next_obs.len() == self.task.obs_dim
                    && act.len() == self.task.act_dim
            }
            Record::Header(_) | Record::Claim(_) | Record::Term(_) | Record::EpisodeEnd(_) => true,
        }
    }

    fn apply(&mut self, record: &Record) {
        match record {
            Record::Header(_) | Record::Term(_) => {}
            Record::Claim(ClaimRecord { epoch, .. }) => self.epoch = self.epoch.max(*epoch),
            Record::Transition(TransitionRecord {
                agent,
                episode,
                obs,
                act,
                origin,
                next_obs,
                reward,
                ..
            }) => {
                self.transitions.push(obs, act, *reward, next_obs);
                self.origins.push(*origin);
                let index = match self.agents.iter().position(|a| a == agent) {
                    Some(index) => index,
                    None => {
                        self.agents.push(agent.clone());
                        self.agents.len() - 1
                    }
                };
                self.owners.push((index as u32, *episode));
            }
            Record::EpisodeEnd(EpisodeEndRecord {
                agent,
                episode,
                steps,
                episode_return,
                end,
                ..
            }) => {
                if *end == EpisodeEnd::Terminated {
                    self.mark_last_terminated(agent, *episode);
                }
                self.episodes.push(EpisodeSummary {
                    agent: agent.clone(),
                    episode: *episode,
                    steps: *steps,
                    episode_return: *episode_return,
                    end: *end,
                });
            }
        }
    }

    /// Marks the last stored transition of `agent`'s `episode` as the one it terminated with:
    /// an agent's transitions are stored in step order, and its episode's end after them, so
    /// the newest transition of that episode is its last. The search runs from the newest
    /// transition back and stops at the first of the episode's (a few rows back: the other
    /// agents' steps since). An episode with no transition in memory marks nothing.
    fn mark_last_terminated(&mut self, agent: &str, episode: u32) {
        let Some(index) = self.agents.iter().position(|a| a == agent) else {
            return;
        };
        let owner = (index as u32, episode);
        if let Some(row) = self.owners.iter().rposition(|o| *o == owner) {
            self.transitions.mark_terminated(row);
        }
    }

    /// Stores `records` together: when this returns `Ok` they are all in the log (as far as
    /// the OS is concerned) and in memory; on error none of them is in either, so the caller
    /// can refuse what they came from and accept it again later. Every transition and episode
    /// end is stored under the buffer's ownership epoch, whatever epoch it was built with.
    pub fn append(&mut self, records: Vec<Record>) -> Result<(), ReplayError> {
        self.store(records, false).map(drop)
    }

    /// As [`ReplayBuffer::append`], and the records are forced to disk before they count: if
    /// the sync fails they are in neither the log nor memory (see
    /// [`ReplayLog::append_synced`]), and the caller refuses what they came from.
    /// Returns the time the sync took (`None` for a buffer in memory only).
    pub fn append_synced(
        &mut self,
        records: Vec<Record>,
    ) -> Result<Option<std::time::Duration>, ReplayError> {
        self.store(records, true)
    }

    fn store(
        &mut self,
        mut records: Vec<Record>,
        synced: bool,
    ) -> Result<Option<std::time::Duration>, ReplayError> {
        for record in &mut records {
            record.set_epoch(self.epoch);
        }
        if let Some(record) = records.iter().find(|r| !self.fits(r)) {
            return Err(ReplayError::Dimension {
                record: format!("{record:?}"),
            });
        }
        let mut sync_took = None;
        if let Some(log) = &mut self.log {
            if synced {
                sync_took = Some(log.append_synced(&records)?);
            } else {
                log.append(&records)?;
            }
        }
        for record in &records {
            self.apply(record);
        }
        if records.iter().any(|r| matches!(r, Record::EpisodeEnd(_))) {
            self.evict()?;
        }
        Ok(sync_took)
    }

    /// The ownership epoch this buffer writes under.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// Stale records skipped when the log was opened.
    pub fn stale_skipped(&self) -> usize {
        self.stale_skipped
    }

    /// Bounds the transitions kept to `capacity` (`None`: unbounded), evicting at once if the
    /// buffer holds more.
    pub fn set_capacity(&mut self, capacity: Option<usize>) -> Result<(), ReplayError> {
        self.capacity = capacity;
        self.evict()
    }

    /// Evicts the transitions of the oldest finished episodes from memory until at most
    /// `capacity` are left (episodes in progress are never evicted). Their records leave the
    /// log when [`compact_log`] runs (see [`ReplayBuffer::compaction_due`]).
    fn evict(&mut self) -> Result<(), ReplayError> {
        let Some(capacity) = self.capacity else {
            return Ok(());
        };
        let mut excess = self.len().saturating_sub(capacity);
        if excess == 0 {
            return Ok(());
        }
        let mut counts: HashMap<(u32, u32), usize> = HashMap::new();
        for owner in &self.owners {
            *counts.entry(*owner).or_default() += 1;
        }
        let mut dropped: HashSet<(u32, u32)> = HashSet::new();
        for episode in &self.episodes {
            if excess == 0 {
                break;
            }
            let Some(agent) = self.agents.iter().position(|a| *a == episode.agent) else {
                continue;
            };
            let key = (agent as u32, episode.episode);
            if let Some(&n) = counts.get(&key)
                && dropped.insert(key)
            {
                excess = excess.saturating_sub(n);
                self.evicted
                    .insert((episode.agent.clone(), episode.episode));
            }
        }
        if dropped.is_empty() {
            return Ok(());
        }
        let keep: Vec<bool> = self.owners.iter().map(|o| !dropped.contains(o)).collect();
        let before = self.len();
        self.transitions.retain(|i| keep[i]);
        let mut row = 0;
        self.origins.retain(|_| {
            row += 1;
            keep[row - 1]
        });
        self.owners.retain(|o| !dropped.contains(o));
        self.evicted_on_disk += before - self.len();
        tracing::info!(
            episodes = dropped.len(),
            transitions = before - self.len(),
            kept = self.len(),
            "evicted the oldest episodes from the replay buffer"
        );
        Ok(())
    }

    /// Whether the log should be compacted: the evicted records on disk outnumber the kept
    /// ones, and no compaction is under way.
    pub fn compaction_due(&self) -> bool {
        self.log.is_some()
            && !self.compacting
            && self.evicted_on_disk > 0
            && self.evicted_on_disk >= self.len().max(1)
    }

    /// Step 1 of [`compact_log`] (under the buffer's lock): starts a compaction if one is due.
    fn start_compaction(&mut self) -> Result<Option<Compaction>, ReplayError> {
        if !self.compaction_due() {
            return Ok(None);
        }
        let Some(log) = &mut self.log else {
            return Ok(None);
        };
        let Some(root) = self.root.clone() else {
            return Ok(None);
        };
        let current = segments::SegmentId::parse(&format!(
            "{}/{}",
            segments::DIR,
            log.path()
                .file_name()
                .and_then(|n| n.to_str())
                .unwrap_or_default()
        ));
        let target = segments::next_segment(&root, current, self.token)?;
        let evicted = self.evicted.clone();
        let dropped = evicted.clone();
        let plan = RewritePlan {
            target: root.join(target.name()),
            head: vec![
                Record::Header(HeaderRecord {
                    task: self.task.name().to_string(),
                    obs_dim: self.task.obs_dim as u32,
                    act_dim: self.task.act_dim as u32,
                }),
                // A base: the new segment holds everything kept, so no earlier one counts.
                Record::Term(TermRecord {
                    epoch: self.token,
                    planner: self.planner.clone(),
                    reads: Vec::new(),
                }),
            ],
            earlier: self.earlier.clone(),
            held_epoch: self.token,
            newer_term: Box::new(move || segments::newest_token(&root)),
        };
        let rewrite = log.start_rewrite(plan, move |record| match record {
            Record::Transition(TransitionRecord { agent, episode, .. }) => {
                !dropped.contains(&(agent.clone(), *episode))
            }
            Record::Header(_) | Record::Claim(_) | Record::Term(_) | Record::EpisodeEnd(_) => true,
        })?;
        self.compacting = true;
        Ok(Some(Compaction {
            rewrite,
            evicted,
            transitions: self.evicted_on_disk,
        }))
    }

    /// Step 3 of [`compact_log`] (under the buffer's lock): puts the compacted file in place,
    /// or hands the job back if records were appended since its last copy. Once in place, the
    /// segments it supersedes are in `superseded`, for [`compact_log`] to remove once the new
    /// one is durable.
    fn finish_compaction(&mut self, job: Compaction) -> Result<Option<Compaction>, ReplayError> {
        let Compaction {
            rewrite,
            evicted,
            transitions,
        } = job;
        let Some(log) = &mut self.log else {
            self.compacting = false;
            rewrite.abandon();
            return Ok(None);
        };
        let before = log.path().to_path_buf();
        match log.finish_rewrite(rewrite) {
            Ok(Some(rewrite)) => Ok(Some(Compaction {
                rewrite,
                evicted,
                transitions,
            })),
            Ok(None) => {
                self.superseded = std::mem::take(&mut self.earlier)
                    .into_iter()
                    .map(|(path, _)| path)
                    .chain([before])
                    .collect();
                tracing::info!(path = %log.path().display(), removed = transitions, kept = self.transitions.len(), "compacted the replay log");
                self.evicted.retain(|e| !evicted.contains(e));
                self.evicted_on_disk -= transitions;
                self.compacting = false;
                Ok(None)
            }
            Err(e) => {
                self.compacting = false;
                Err(e.into())
            }
        }
    }

    /// Gives a compaction up; the log stays as it is and the next one starts afresh.
    fn abandon_compaction(&mut self, job: Compaction) {
        self.compacting = false;
        job.rewrite.abandon();
    }

    /// Compacts the log now if it is due, for a caller that holds the buffer alone (opening a
    /// run, tests): [`compact_log`] with a lock nobody else takes.
    pub fn compact_if_due(&mut self) -> Result<(), ReplayError> {
        let only = std::cell::RefCell::new(self);
        compact_log(|| std::cell::RefMut::map(only.borrow_mut(), |b| &mut **b))
    }

    /// Marks this term's segment as read by other planners (a fleet: a newer owner records
    /// how far it read it): a failed write's bytes are never cut from it from now on.
    pub fn share_log(&mut self) {
        if let Some(log) = &mut self.log {
            log.share();
        }
    }

    /// A handle that syncs the log to disk without holding the buffer (`None` in memory).
    pub fn syncer(&self) -> Option<LogSyncer> {
        self.log.as_ref().map(ReplayLog::syncer)
    }

    pub fn transitions(&self) -> &Transitions {
        &self.transitions
    }

    /// Which action each stored transition holds (in the order of [`Self::transitions`]).
    pub fn origins(&self) -> &[ActionOrigin] {
        &self.origins
    }

    pub fn episodes(&self) -> &[EpisodeSummary] {
        &self.episodes
    }

    pub fn len(&self) -> usize {
        self.transitions.len()
    }

    /// Bytes of the run's data on disk: the lengths that count of the earlier segments and
    /// this term's segment (0 for a buffer in memory only).
    pub fn log_bytes(&self) -> u64 {
        self.earlier.iter().map(|(_, len)| len).sum::<u64>()
            + self.log.as_ref().map_or(0, ReplayLog::len_bytes)
    }

    pub fn is_empty(&self) -> bool {
        self.transitions.is_empty()
    }

    /// What opening the log could not read, in words (`None`: nothing was lost).
    pub fn damage(&self) -> Option<&str> {
        self.damage.as_deref()
    }
}

/// A compaction under way: the log's rewrite, and the evictions it removes from disk.
#[derive(Debug)]
struct Compaction {
    rewrite: Rewrite,
    evicted: HashSet<(String, u32)>,
    /// Transitions evicted from memory whose records this rewrite drops.
    transitions: usize,
}

/// Catch-up copies a compaction makes before it gives up for now (records kept being appended
/// between its copy and its swap); the next episode end tries again.
const CATCH_UPS: usize = 4;

/// Rewrites the log without the records of evicted episodes, if due, taking the buffer's lock
/// through `lock` only to start and to swap files: the copying and its fsyncs run with no lock
/// held, so the run's agents keep storing (and its trainer keeps reading) meanwhile, and what
/// they append during the copy is copied too before the swap (see [`ReplayLog::start_rewrite`]).
///
/// The compaction writes a new segment of this term holding everything kept (see
/// [`segments`]); the segments it supersedes are removed once it is durable, and only while
/// the buffer's [`OwnerCheck`] says this planner still owns the run. A planner that lost the
/// run (a newer term has a segment) does not compact: the compaction is skipped, and this
/// planner steps down at its next ownership check.
pub fn compact_log<G: DerefMut<Target = ReplayBuffer>>(
    lock: impl Fn() -> G,
) -> Result<(), ReplayError> {
    let Some(mut job) = lock().start_compaction()? else {
        return Ok(());
    };
    for _ in 0..CATCH_UPS {
        if let Err(e) = job.rewrite.copy() {
            lock().abandon_compaction(job);
            return match e {
                LogError::Fenced { path, held, found } => {
                    tracing::warn!(path = %path.display(), held, found, "the run was claimed by another planner; the log is not compacted");
                    Ok(())
                }
                e => Err(e.into()),
            };
        }
        let behind = match lock().finish_compaction(job) {
            Err(ReplayError::Log(LogError::Fenced { path, held, found })) => {
                tracing::warn!(path = %path.display(), held, found, "the run was claimed by another planner; the log is not compacted");
                return Ok(());
            }
            behind => behind?,
        };
        match behind {
            Some(again) => job = again,
            None => {
                // The new file's name in its directory becomes durable here, off the lock;
                // then the segments it supersedes go, while this planner still owns the run.
                let (syncer, superseded, root, still_owner) = {
                    let mut buffer = lock();
                    (
                        buffer.syncer(),
                        std::mem::take(&mut buffer.superseded),
                        buffer.root.clone(),
                        buffer.still_owner.clone(),
                    )
                };
                if let Some(syncer) = syncer {
                    syncer.sync()?;
                }
                if let Some(root) = root {
                    segments::remove(&root, &superseded, &|| still_owner.holds());
                }
                return Ok(());
            }
        }
    }
    tracing::info!("the replay log kept growing during its compaction; it is compacted later");
    lock().abandon_compaction(job);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::Builtin;

    const PLANNED: ActionOrigin = ActionOrigin::Planned;

    /// A transition of `agent`'s `episode` at `step` with the cartpole's dimensions.
    fn transition(agent: &str, episode: u32, step: u32, reward: f32) -> Record {
        Record::Transition(TransitionRecord {
            epoch: 0,
            agent: agent.into(),
            episode,
            step,
            obs: vec![step as f32; 4],
            act: vec![0.1],
            origin: PLANNED,
            next_obs: vec![step as f32 + 1.0; 4],
            reward,
        })
    }

    /// The run's segment files, oldest first.
    fn segment_files(root: &std::path::Path) -> Vec<std::path::PathBuf> {
        segments::list(root)
            .unwrap()
            .into_iter()
            .map(|id| root.join(id.name()))
            .collect()
    }

    /// Stores one finished 10-step episode of agent `a` in the log at `path` and closes it;
    /// returns what the buffer held and the episode's summary.
    fn store_one_episode(
        path: &std::path::Path,
        task: &'static Task,
    ) -> (Transitions, EpisodeSummary) {
        let mut buffer = ReplayBuffer::open(path, task, 1, "p").unwrap();
        for step in 0..10 {
            buffer.append(vec![transition("a", 0, step, 0.5)]).unwrap();
        }
        let summary = EpisodeSummary {
            agent: "a".into(),
            episode: 0,
            steps: 10,
            episode_return: 5.0,
            end: EpisodeEnd::TimeLimit,
        };
        buffer.append(vec![summary.clone().into()]).unwrap();
        (buffer.transitions().clone(), summary)
    }

    #[test]
    fn a_reopened_buffer_holds_everything_stored() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let (snapshot, summary) = store_one_episode(&path, task);

        let reopened = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert_eq!(reopened.transitions(), &snapshot);
        assert_eq!(reopened.episodes(), &[summary]);
        let err = ReplayBuffer::open(&path, Builtin::Ant.task(), 1, "p").unwrap_err();
        assert!(err.to_string().contains("holds task cartpole"), "{err}");
    }

    /// A damaged header record costs only itself: the run resumes with every transition and
    /// episode, says what was lost, and a log that never had a header is still refused.
    #[test]
    fn a_damaged_header_costs_only_the_header() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        assert_eq!(
            ReplayBuffer::open(&path, task, 1, "p").unwrap().damage(),
            None
        );
        let (snapshot, summary) = store_one_episode(&path, task);
        // The task's name appears first in the header record: damage one of its bytes, in
        // every segment (each starts with a header).
        for file in segment_files(&path) {
            let mut bytes = std::fs::read(&file).unwrap();
            let at = bytes
                .windows(b"cartpole".len())
                .position(|w| w == b"cartpole")
                .expect("the header names the task");
            bytes[at + 2] ^= 0xff;
            std::fs::write(&file, &bytes).unwrap();
        }
        let mut reopened = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert_eq!(reopened.transitions(), &snapshot);
        assert_eq!(reopened.episodes(), std::slice::from_ref(&summary));
        let damage = reopened.damage().expect("the damage is reported");
        assert!(damage.contains("header record is damaged"), "{damage}");
        // It stores on, and opens again the same way.
        reopened.append(vec![transition("a", 1, 0, 1.0)]).unwrap();
        drop(reopened);
        let again = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert_eq!(again.len(), 11);
        // A file of records with no header and no damage is not a replay log of this run.
        let foreign = dir.path().join("foreign");
        let mut log = ReplayLog::open(&foreign.join(segments::LEGACY)).unwrap().0;
        log.append(&[transition("a", 0, 0, 0.5)]).unwrap();
        drop(log);
        let err = ReplayBuffer::open(&foreign, task, 1, "p").unwrap_err();
        assert!(matches!(err, ReplayError::MissingHeader { .. }), "{err}");
    }

    #[test]
    fn an_episode_left_open_is_recorded_as_interrupted_on_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let mut buffer = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        for step in 0..3 {
            buffer
                .append(vec![
                    transition("a", 4, step, 0.5),
                    transition("b", 0, step, 1.0),
                ])
                .unwrap();
        }
        buffer
            .append(vec![
                EpisodeSummary {
                    agent: "b".into(),
                    episode: 0,
                    steps: 3,
                    episode_return: 3.0,
                    end: EpisodeEnd::Terminated,
                }
                .into(),
            ])
            .unwrap();
        drop(buffer); // as if the daemon was killed: a's episode 4 never ended

        let reopened = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert_eq!(reopened.len(), 6, "every stored transition is kept");
        // b's episode terminated: its last step (the newest row, after a's) is marked as the
        // end a learned termination trains on; a's interrupted one marks nothing.
        assert_eq!(
            reopened.transitions().terminated(),
            &[false, false, false, false, false, true]
        );
        let interrupted = EpisodeSummary {
            agent: "a".into(),
            episode: 4,
            steps: 3,
            episode_return: 1.5,
            end: EpisodeEnd::Interrupted,
        };
        assert_eq!(reopened.episodes().len(), 2);
        assert_eq!(reopened.episodes()[1], interrupted);
        drop(reopened);
        // Recorded once: opening again finds nothing left open.
        let again = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert_eq!(again.episodes().len(), 2);
    }

    #[test]
    fn an_intact_record_of_the_wrong_dimension_is_skipped_on_reopening() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        drop(ReplayBuffer::open(&path, task, 1, "p").unwrap());
        // Written straight to the log (as a buggy older build or a hand edit could): the
        // buffer itself refuses such a record.
        let newest = segment_files(&path).pop().unwrap();
        let (mut log, _) = ReplayLog::open(&newest).unwrap();
        let mut wrong = transition("a", 0, 1, 1.0);
        if let Record::Transition(TransitionRecord { obs, .. }) = &mut wrong {
            obs.push(9.0);
        }
        let mut records = [
            transition("a", 0, 0, 1.0),
            wrong.clone(),
            transition("a", 0, 2, 1.0),
        ];
        for record in &mut records {
            record.set_epoch(1);
        }
        log.append(&records).unwrap();
        drop(log);
        let mut reopened = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert_eq!(reopened.len(), 2);
        let err = reopened.append(vec![wrong]).unwrap_err();
        assert!(matches!(err, ReplayError::Dimension { .. }), "{err}");
        assert_eq!(reopened.len(), 2);
    }

    #[test]
    fn an_episode_numbered_u32_max_resumes_without_overflow() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let mut buffer = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        buffer
            .append(vec![transition("a", u32::MAX, u32::MAX, 1.0)])
            .unwrap();
        drop(buffer);
        let reopened = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert_eq!(reopened.episodes()[0].steps, u32::MAX);
    }

    fn episode(agent: &str, episode: u32, steps: u32) -> Vec<Record> {
        let mut records: Vec<Record> = (0..steps)
            .map(|step| transition(agent, episode, step, episode as f32))
            .collect();
        records.push(
            EpisodeSummary {
                agent: agent.into(),
                episode,
                steps,
                episode_return: (episode * steps) as f32,
                end: EpisodeEnd::TimeLimit,
            }
            .into(),
        );
        records
    }

    /// The episode of every transition in the buffer, read back from its rewards.
    fn episodes_held(buffer: &ReplayBuffer) -> Vec<u32> {
        let mut held: Vec<u32> = buffer.owners.iter().map(|&(_, e)| e).collect();
        held.dedup();
        held
    }

    #[test]
    fn a_capacity_evicts_the_oldest_whole_episodes_and_keeps_the_log_bounded() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let mut buffer = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        buffer.set_capacity(Some(10)).unwrap();
        // An episode of agent b stays open the whole time: it is never evicted.
        buffer.append(vec![transition("b", 0, 0, 9.0)]).unwrap();
        for e in 0..20 {
            buffer.append(episode("a", e, 4)).unwrap();
            buffer.compact_if_due().unwrap();
            assert!(buffer.len() <= 10 + 1, "episode {e}: {} kept", buffer.len());
        }
        // a's newest two episodes (8 transitions) and b's open one are kept.
        assert_eq!(buffer.len(), 9);
        assert_eq!(episodes_held(&buffer), vec![0, 18, 19]);
        assert_eq!(buffer.episodes().len(), 20, "summaries are never evicted");
        let kept = buffer.transitions().clone();
        drop(buffer);
        // The log was compacted: it holds at most twice the capacity, plus what is open.
        let unbounded = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        assert!(unbounded.len() <= 2 * 10 + 1, "{} on disk", unbounded.len());
        assert_eq!(
            unbounded.episodes().len(),
            21,
            "b's episode is now interrupted"
        );
        drop(unbounded);
        // Reopened with the same capacity, the buffer holds exactly what it held.
        let mut reopened = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        reopened.set_capacity(Some(10)).unwrap();
        assert_eq!(reopened.transitions(), &kept);
    }

    /// A planner that lost the run and wrote on to its own segment after the new owner read
    /// it: those records are never read, the new owner's are, and the applied actions are
    /// kept as such.
    #[test]
    fn a_stale_writers_appends_after_the_takeover_never_reach_the_run() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let mut old_owner = ReplayBuffer::open(&path, task, 1, "pa").unwrap();
        old_owner.share_log();
        old_owner.append(vec![transition("a", 0, 0, 1.0)]).unwrap();
        let mut new_owner = ReplayBuffer::open(&path, task, 2, "pb").unwrap();
        assert_eq!((new_owner.epoch(), new_owner.len()), (2, 1));
        let mut applied = transition("a", 0, 1, 1.0);
        if let Record::Transition(TransitionRecord { act, origin, .. }) = &mut applied {
            *act = vec![-3.0];
            *origin = ActionOrigin::Applied;
        }
        new_owner.append(vec![applied]).unwrap();
        // The old owner, partitioned, still writes to its own segment under token 1.
        old_owner.append(vec![transition("a", 0, 1, 1.0)]).unwrap();
        old_owner.append(episode("a", 5, 3)).unwrap();
        drop(new_owner);
        // A third owner reads the old owner's segment only as far as the second read it,
        // even though the second owner is gone and the old one wrote on.
        let third = ReplayBuffer::open(&path, task, 3, "pc").unwrap();
        old_owner.append(vec![transition("a", 0, 2, 1.0)]).unwrap();
        drop((old_owner, third));
        let reopened = ReplayBuffer::read(&path, task).unwrap();
        assert_eq!(reopened.epoch(), 3);
        assert_eq!(reopened.len(), 2);
        assert_eq!(reopened.origins(), &[PLANNED, ActionOrigin::Applied]);
        assert_eq!(reopened.transitions().row(1).1, &[-3.0]);
        assert!(
            reopened.episodes().iter().all(|e| e.episode != 5),
            "the stale writer's episode is not in the run"
        );
        // An owner older than the newest segment cannot start a segment.
        let err = ReplayBuffer::open(&path, task, 2, "pb").unwrap_err();
        assert!(
            matches!(err, ReplayError::Log(LogError::Fenced { found: 3, .. })),
            "{err}"
        );
    }

    /// A run stored before segments (one `replay.log`) opens with every record; the file is
    /// never written again, is listed by the first segment, and the first compaction removes it.
    #[test]
    fn a_run_stored_before_segments_opens_and_is_compacted_into_segments() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let legacy = path.join(segments::LEGACY);
        let (mut log, _) = ReplayLog::open(&legacy).unwrap();
        log.append(&[Record::Header(HeaderRecord {
            task: "cartpole".into(),
            obs_dim: 4,
            act_dim: 1,
        })])
        .unwrap();
        log.append(&[Record::Claim(ClaimRecord {
            epoch: 4,
            planner: "old".into(),
        })])
        .unwrap();
        for e in 0..3 {
            let mut records = episode("a", e, 4);
            for record in &mut records {
                record.set_epoch(4);
            }
            log.append(&records).unwrap();
        }
        drop(log);
        let before = std::fs::read(&legacy).unwrap();
        let mut buffer = ReplayBuffer::open(&path, task, 5, "p").unwrap();
        assert_eq!((buffer.len(), buffer.episodes().len()), (12, 3));
        assert_eq!(std::fs::read(&legacy).unwrap(), before, "never written");
        buffer.append(episode("b", 0, 2)).unwrap();
        buffer.set_capacity(Some(4)).unwrap();
        buffer.compact_if_due().unwrap();
        assert!(!legacy.exists(), "superseded by the compacted segment");
        let files = segment_files(&path);
        assert_eq!(files.len(), 1, "{files:?}");
        drop(buffer);
        let reopened = ReplayBuffer::read(&path, task).unwrap();
        assert_eq!(reopened.episodes().len(), 4);
        assert!(reopened.len() <= 8, "{} kept", reopened.len());
    }

    /// Eviction keeps each transition's origin with it; a planner that lost the run does not
    /// compact (its segment would not be part of the run), and a segment a stale writer
    /// created after the takeover is ignored and removed by the next owner.
    #[test]
    fn eviction_keeps_origins_aligned_and_a_fenced_owner_never_compacts() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let mut old_owner = ReplayBuffer::open(&path, task, 1, "pa").unwrap();
        old_owner.set_capacity(Some(4)).unwrap();
        for e in 0..3 {
            let mut records = episode("a", e, 4);
            // Episode e's first step was applied by the agent, the others planned.
            if let Record::Transition(TransitionRecord { origin, .. }) = &mut records[0] {
                *origin = ActionOrigin::Applied;
            }
            old_owner.append(records).unwrap();
            old_owner.compact_if_due().unwrap();
        }
        // Only the newest episode is kept in memory, its origins with it.
        assert_eq!(old_owner.len(), 4);
        assert_eq!(
            old_owner.origins(),
            &[ActionOrigin::Applied, PLANNED, PLANNED, PLANNED]
        );
        assert_eq!(segment_files(&path).len(), 1, "compacted into one segment");
        let mut new_owner = ReplayBuffer::open(&path, task, 2, "pb").unwrap();
        assert_eq!(new_owner.len(), 4);
        new_owner.append(episode("b", 0, 2)).unwrap();
        let files = segment_files(&path);
        // The old owner, fenced without knowing, evicts again: it compacts nothing.
        for e in 3..6 {
            old_owner.append(episode("a", e, 4)).unwrap();
            old_owner.compact_if_due().unwrap();
        }
        assert_eq!(segment_files(&path), files, "no segment made or removed");
        // A segment the stale writer managed to create anyway is ignored, and the next owner
        // removes it.
        let late = path.join(segments::SegmentId::Term { token: 1, seq: 9 }.name());
        std::fs::copy(&files[0], &late).unwrap();
        drop((old_owner, new_owner));
        let reopened = ReplayBuffer::open(&path, task, 3, "pc").unwrap();
        assert_eq!(reopened.epoch(), 3);
        assert_eq!(
            reopened.len(),
            6,
            "the new owner's transitions are all kept, the stale ones none"
        );
        assert!(!late.exists(), "garbage removed at opening");
    }

    /// The buffer's lock is free while a compaction copies and fsyncs (its steps 1 and 3 are
    /// the only ones that take it): agents append meanwhile, the compaction catches up with
    /// what they wrote before it swaps files, and nothing they stored is lost.
    #[test]
    fn appends_during_a_compaction_are_caught_up_and_kept() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let buffer = std::sync::Mutex::new(ReplayBuffer::open(&path, task, 1, "p").unwrap());
        let lock = || buffer.lock().unwrap();
        lock().set_capacity(Some(4)).unwrap();
        for e in 0..3 {
            lock().append(episode("a", e, 4)).unwrap();
        }
        assert!(lock().compaction_due(), "8 evicted on disk, 4 kept");

        let mut job = lock().start_compaction().unwrap().expect("due");
        assert!(!lock().compaction_due(), "one compaction at a time");
        // Step 2 runs with no lock held: an agent stores a whole episode in the middle of it.
        job.rewrite.copy().unwrap();
        lock().append(episode("b", 0, 3)).unwrap();
        let job = lock()
            .finish_compaction(job)
            .unwrap()
            .expect("the log grew since the copy: the job comes back");
        let mut job = job;
        job.rewrite.copy().unwrap();
        assert!(lock().finish_compaction(job).unwrap().is_none(), "swapped");
        // Stored after the swap, through the new file.
        lock().append(episode("c", 0, 2)).unwrap();
        lock().syncer().unwrap().sync().unwrap();
        let kept = lock().transitions().clone();
        drop(buffer);

        let reopened = ReplayBuffer::open(&path, task, 1, "p").unwrap();
        let agents: Vec<&str> = reopened
            .episodes()
            .iter()
            .map(|e| e.agent.as_str())
            .collect();
        assert_eq!(agents, ["a", "a", "a", "b", "c"], "every summary is kept");
        assert_eq!(
            reopened.len(),
            4 + 3 + 2,
            "a's evicted episodes left the log, nothing else"
        );
        let mut bounded = reopened;
        bounded.set_capacity(Some(4)).unwrap();
        assert_eq!(bounded.transitions(), &kept);
    }

    /// A newer term that starts during the copy stops the compaction: no segment of the
    /// fenced term is made, nothing is removed, and the half-written copy is removed.
    #[test]
    fn a_takeover_during_a_compaction_fences_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().to_path_buf();
        let task = Builtin::Cartpole.task();
        let old_owner = std::sync::Mutex::new(ReplayBuffer::open(&path, task, 1, "pa").unwrap());
        let lock = || old_owner.lock().unwrap();
        lock().set_capacity(Some(4)).unwrap();
        for e in 0..3 {
            lock().append(episode("a", e, 4)).unwrap();
        }
        let mut job = lock().start_compaction().unwrap().expect("due");
        job.rewrite.copy().unwrap();
        let new_owner = ReplayBuffer::open(&path, task, 2, "pb").unwrap();
        let files = segment_files(&path);
        let err = lock().finish_compaction(job).unwrap_err();
        assert!(
            matches!(err, ReplayError::Log(LogError::Fenced { found: 2, .. })),
            "{err}"
        );
        assert_eq!(segment_files(&path), files, "nothing made or removed");
        let leftovers: Vec<_> = std::fs::read_dir(path.join(segments::DIR))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .filter(|n| n.to_string_lossy().contains("compacting"))
            .collect();
        assert!(leftovers.is_empty(), "{leftovers:?}");
        // The driver reports the same refusal as a skipped compaction, not a failure.
        compact_log(lock).unwrap();
        assert_eq!(segment_files(&path), files);
        drop(new_owner);
        assert_eq!(ReplayBuffer::read(&path, task).unwrap().len(), 12);
    }
}
