//! A run's replay on disk: one file (*segment*) per ownership term, so that no two planners
//! ever append to one file.
//!
//! ```text
//! {run}/replay.log                           the run's log before segments (read only)
//! {run}/replay/{token:020}-{seq:06}.log      a segment: term `token`, its `seq`-th file
//! ```
//!
//! A planner that opens a run at fencing token `token` reads the run's data (below), then
//! creates a new segment of its own holding the header and a [`Record::Term`] that names every
//! earlier segment the data continues from, each with its length *as this term read it*
//! (the end of its last intact record), and appends only to that segment. Segments order by
//! `(token, seq)`; a term opening a run whose newest segment is of its own token (a
//! compaction's, or a reopening by the same owner) takes the next `seq`.
//!
//! **Reading a run** starts from its newest segment: its term lists what counts before it, so
//! the run's data is each listed segment up to its listed length, in order, then the newest
//! segment whole. Hence the rule for a stale writer (a planner that lost the run and has not
//! noticed): whatever it appends to its own segment after a newer term read that segment lies
//! beyond the listed length and is never read, and a segment it creates after that (a late
//! compaction) is listed by no newer term and is ignored. A newer owner opens only after the
//! stale one's etcd lease expired, which is after the stale one stopped acknowledging by its
//! own clock, so nothing acknowledged lies beyond a listed length.
//!
//! **Compaction** writes a new segment of the current term holding the kept records of all
//! the others, whose term lists nothing (it is a base: everything before it is superseded);
//! the superseded segments are removed by their run's owner once the new one is durable. A
//! segment that is older than the newest and listed by no term is garbage: the next owner
//! removes it when it opens the run.
//!
//! A run stored before segments has only `replay.log`: its first term lists it like any
//! earlier segment, and it is never written again (the first compaction removes it).

use super::log::{
    ClaimRecord, LogError, LogFile, Record, Recovered, ReplayLog, SegmentRead, TermRecord,
};
use std::path::{Path, PathBuf};

/// The log of a run stored before segments, relative to the run's directory.
pub const LEGACY: &str = "replay.log";

/// The directory of the segments, relative to the run's directory.
pub const DIR: &str = "replay";

/// Where a segment stands in its run's order: the oldest is the log from before segments.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum SegmentId {
    Legacy,
    Term { token: u64, seq: u32 },
}

impl SegmentId {
    /// The file's name relative to the run's directory.
    pub fn name(self) -> String {
        match self {
            SegmentId::Legacy => LEGACY.to_string(),
            SegmentId::Term { token, seq } => format!("{DIR}/{token:020}-{seq:06}.log"),
        }
    }

    /// The segment a name relative to the run's directory stands for (`None`: not a segment).
    pub fn parse(name: &str) -> Option<Self> {
        if name == LEGACY {
            return Some(SegmentId::Legacy);
        }
        let stem = name.strip_prefix(DIR)?.strip_prefix('/')?;
        let (token, seq) = stem.strip_suffix(".log")?.split_once('-')?;
        let id = SegmentId::Term {
            token: token.parse().ok()?,
            seq: seq.parse().ok()?,
        };
        (id.name() == name).then_some(id)
    }

    fn token(self) -> Option<u64> {
        match self {
            SegmentId::Legacy => None,
            SegmentId::Term { token, .. } => Some(token),
        }
    }
}

/// Every segment of the run in directory `root`, oldest first (none for a new run).
pub fn list(root: &Path) -> std::io::Result<Vec<SegmentId>> {
    let mut found = Vec::new();
    if root.join(LEGACY).is_file() {
        found.push(SegmentId::Legacy);
    }
    match std::fs::read_dir(root.join(DIR)) {
        Ok(entries) => {
            for entry in entries {
                let entry = entry?;
                let Some(name) = entry.file_name().to_str().map(|n| format!("{DIR}/{n}")) else {
                    continue;
                };
                if let Some(id) = SegmentId::parse(&name) {
                    found.push(id);
                }
            }
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(e),
    }
    found.sort();
    Ok(found)
}

/// The newest term that has a segment in `root` (`None`: none, or only the legacy log).
pub fn newest_token(root: &Path) -> Option<u64> {
    list(root).ok()?.last().and_then(|id| id.token())
}

/// Bytes of every segment file of the run in `root` (what it holds on disk).
pub fn bytes_on_disk(root: &Path) -> u64 {
    list(root).map_or(0, |ids| {
        ids.iter()
            .filter_map(|id| std::fs::metadata(root.join(id.name())).ok())
            .map(|m| m.len())
            .sum()
    })
}

/// When the run in `root` last stored anything (its newest segment's last write).
pub fn last_written(root: &Path) -> Option<std::time::SystemTime> {
    let newest = list(root).ok()?.pop()?;
    std::fs::metadata(root.join(newest.name()))
        .and_then(|m| m.modified())
        .ok()
}

/// The run's data as its newest segment says it is (see the module's documentation).
#[derive(Debug, Default)]
pub struct View {
    /// Every record, in order: the first header found first, then the stream of claims,
    /// transitions and episode ends (no further headers, no terms).
    pub recovered: Recovered,
    /// The segments read and their lengths that count, oldest first, the newest included:
    /// what a new term continues from.
    pub reads: Vec<SegmentRead>,
    /// The newest segment.
    pub newest: Option<SegmentId>,
    /// Segments older than the newest that no term lists (superseded by a compaction, or
    /// created by a stale writer after a newer term read the run).
    pub garbage: Vec<SegmentId>,
    /// Segments a term lists that are missing or shorter than listed (with what was found).
    pub missing: Vec<String>,
}

impl View {
    /// Bytes of the data the view holds (the lengths that count).
    pub fn bytes(&self) -> u64 {
        self.reads.iter().map(|r| r.len).sum()
    }
}

/// Reads the run in directory `root` without writing anything (safe beside its owner).
pub fn read(root: &Path) -> Result<View, LogError> {
    let ids = list(root).map_err(|source| LogError::Io {
        path: root.join(DIR),
        source,
    })?;
    let Some(&newest) = ids.last() else {
        return Ok(View::default());
    };
    let (newest_rec, newest_len) = ReplayLog::read_prefix(&root.join(newest.name()), None)?;
    let term_reads = newest_rec.records.iter().take(2).find_map(|r| match r {
        Record::Term(TermRecord { reads, .. }) => Some(reads.clone()),
        _ => None,
    });
    let mut view = View {
        newest: Some(newest),
        ..View::default()
    };
    let earlier: Vec<SegmentRead> = match term_reads {
        Some(reads) => reads,
        None if newest == SegmentId::Legacy => Vec::new(),
        None => {
            // The newest segment's term is damaged: read every older segment whole rather
            // than lose what they hold, and say so.
            tracing::warn!(path = %root.join(newest.name()).display(), "the newest replay segment's term record is damaged; reading every older segment whole");
            view.missing
                .push(format!("{} (its term record is damaged)", newest.name()));
            let mut reads = Vec::new();
            for id in &ids[..ids.len() - 1] {
                let (_, len) = ReplayLog::read_prefix(&root.join(id.name()), None)?;
                reads.push(SegmentRead {
                    name: id.name(),
                    len,
                });
            }
            reads
        }
    };
    let mut parts = Vec::new();
    for listed in &earlier {
        if SegmentId::parse(&listed.name).is_none() {
            view.missing
                .push(format!("{} (not a segment name)", listed.name));
            continue;
        }
        let path = root.join(&listed.name);
        let (recovered, found) = ReplayLog::read_prefix(&path, Some(listed.len))?;
        if found < listed.len {
            let on_disk = std::fs::metadata(&path).map(|m| m.len());
            view.missing.push(match on_disk {
                Ok(len) => format!("{} ({len} of {} bytes)", listed.name, listed.len),
                Err(_) => format!("{} (missing)", listed.name),
            });
        }
        parts.push(recovered);
        view.reads.push(listed.clone());
    }
    parts.push(newest_rec);
    view.reads.push(SegmentRead {
        name: newest.name(),
        len: newest_len,
    });
    if !view.missing.is_empty() {
        tracing::warn!(run = %root.display(), missing = ?view.missing, "replay segments listed by the run's newest term are missing or short");
    }
    view.garbage = ids[..ids.len() - 1]
        .iter()
        .filter(|id| !view.reads.iter().any(|r| r.name == id.name()))
        .copied()
        .collect();
    let mut header = None;
    let mut stream = Vec::new();
    for part in parts {
        view.recovered.damaged_regions += part.damaged_regions;
        view.recovered.damaged_bytes += part.damaged_bytes;
        view.recovered.truncated_bytes += part.truncated_bytes;
        for record in part.records {
            match record {
                Record::Header(_) => {
                    header.get_or_insert(record);
                }
                Record::Term(_) => {}
                record => stream.push(record),
            }
        }
    }
    view.recovered.records = header.into_iter().chain(stream).collect();
    Ok(view)
}

/// A term's segment, newly created: what it continues from and its writer.
pub struct Opened {
    pub log: ReplayLog,
    /// The earlier segments it continues from, with their paths and lengths that count.
    pub earlier: Vec<(PathBuf, u64)>,
}

/// Creates the segment of term `token` held by `planner` in the run at `root`, continuing
/// from `view` (read just before), holding `header`, the term and a claim; it writes through
/// `wrap(file)`. Refused with [`LogError::Fenced`] if a newer term already has a segment.
pub fn create(
    root: &Path,
    view: &View,
    header: Record,
    (token, planner): (u64, &str),
    wrap: impl FnOnce(std::fs::File) -> Box<dyn LogFile>,
) -> Result<Opened, LogError> {
    let id = next_segment(root, view.newest, token)?;
    let head = [
        header,
        Record::Term(TermRecord {
            epoch: token,
            planner: planner.to_string(),
            reads: view.reads.clone(),
        }),
        Record::Claim(ClaimRecord {
            epoch: token,
            planner: planner.to_string(),
        }),
    ];
    let log = ReplayLog::create_with(&root.join(id.name()), &head, wrap)?;
    let earlier = view
        .reads
        .iter()
        .map(|r| (root.join(&r.name), r.len))
        .collect();
    Ok(Opened { log, earlier })
}

/// The segment term `token` writes next, after `newest`; refused if `newest` is of a newer term.
pub fn next_segment(
    root: &Path,
    newest: Option<SegmentId>,
    token: u64,
) -> Result<SegmentId, LogError> {
    match newest {
        Some(SegmentId::Term { token: found, seq }) if found == token => Ok(SegmentId::Term {
            token,
            seq: seq + 1,
        }),
        Some(SegmentId::Term { token: found, .. }) if found > token => Err(LogError::Fenced {
            path: root.join(DIR),
            held: token,
            found,
        }),
        _ => Ok(SegmentId::Term { token, seq: 0 }),
    }
}

/// Removes segments of the run at `root` (superseded or garbage), if `may_remove` still says
/// this planner owns the run just before each one. Failures are logged: a segment left behind
/// is listed by no term and is removed at the next opening.
pub fn remove(root: &Path, segments: &[PathBuf], may_remove: &dyn Fn() -> bool) {
    for path in segments {
        if !may_remove() {
            tracing::info!(run = %root.display(), "no longer sure to own the run: superseded replay segments are left for its next owner");
            return;
        }
        match std::fs::remove_file(path) {
            Ok(()) => tracing::info!(path = %path.display(), "removed a superseded replay segment"),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                tracing::warn!(path = %path.display(), error = %e, "cannot remove a superseded replay segment")
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segment_names_parse_back_and_order_by_term_then_sequence() {
        let ids = [
            SegmentId::Legacy,
            SegmentId::Term { token: 7, seq: 0 },
            SegmentId::Term { token: 7, seq: 1 },
            SegmentId::Term { token: 12, seq: 0 },
        ];
        for id in ids {
            assert_eq!(SegmentId::parse(&id.name()), Some(id));
        }
        assert!(ids.windows(2).all(|w| w[0] < w[1]));
        // Names differing only in zero padding, and strangers, are not segments.
        for name in [
            "replay/7-0.log",
            "replay/00000000000000000007-000000.log.tmp",
            "replay/../replay.log",
            "other.log",
        ] {
            assert_eq!(SegmentId::parse(name), None, "{name}");
        }
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join(DIR)).unwrap();
        for id in ids.iter().rev() {
            std::fs::write(dir.path().join(id.name()), b"").unwrap();
        }
        std::fs::write(dir.path().join(DIR).join("stray.log.compacting"), b"").unwrap();
        assert_eq!(list(dir.path()).unwrap(), ids);
        assert_eq!(newest_token(dir.path()), Some(12));
        // A term may not start behind the newest one; the same term takes the next file.
        assert!(next_segment(dir.path(), Some(ids[3]), 11).is_err());
        assert_eq!(
            next_segment(dir.path(), Some(ids[3]), 12).unwrap(),
            SegmentId::Term { token: 12, seq: 1 }
        );
    }
}
