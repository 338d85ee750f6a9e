//! `planner-service status`: asks running planners for their status and prints it as a table
//! (or as the raw JSON with `--json`).
//!
//! The daemon's side of this exchange is `service/status.rs`: every planner serves a JSON report
//! on `{prefix}/planners/{id}/status`. This client queries one planner or, by default, all of
//! them with a wildcard, through the same explicit endpoints (or router) the agents use.
//!
//! It joins as a Zenoh *client*, not a peer: a fresh peer routes a query by the queryables it
//! has heard of, and right after connecting to a router it has heard of none yet, so its query
//! went nowhere and ended at once with no answer (what made `status` through a router fail
//! most of the time). A client hands every query to its router, which knows all queryables.
//! It also reads the planners' liveliness tokens first, so it knows whom to expect, asks again
//! those that did not answer, and names those still silent at the deadline.
//!
//! The report is read into this module's own lenient mirror of the daemon's types: unknown
//! fields are ignored and missing ones take defaults, so an operator's `status` keeps working
//! against a planner of another release instead of refusing the whole report.

use anyhow::{Context, Result, bail};
use proto::Keys;
use serde::Deserialize;
use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Duration;
use zenoh::query::{ConsolidationMode, QueryTarget};

/// How many of a run's most recent returns the table shows (`--json` has all the report has).
const RETURNS_SHOWN: usize = 5;

#[derive(clap::Args, Debug)]
pub struct StatusArgs {
    /// Zenoh endpoint of the planner (its --listen) or of a router, e.g. tcp/127.0.0.1:7447
    /// (repeatable).
    #[arg(long, env = "EBMPC_CONNECT", value_delimiter = ',')]
    connect: Vec<String>,
    /// Zenoh JSON5 config to start from (TLS to a router, say); --connect applies on top.
    #[arg(long, env = "EBMPC_ZENOH_CONFIG")]
    zenoh_config: Option<PathBuf>,
    /// Key prefix shared with the planners.
    #[arg(long, env = "EBMPC_PREFIX", default_value = proto::keys::DEFAULT_PREFIX)]
    prefix: String,
    /// Only this planner (its id); by default every planner that answers.
    #[arg(long)]
    planner: Option<String>,
    /// Print the reports as a JSON array, one object per planner (for scripts).
    #[arg(long)]
    json: bool,
    /// How long to wait for the planners' answers, in seconds.
    #[arg(long, default_value_t = 5.0)]
    timeout: f64,
}

/// One planner's report (a lenient mirror of `service::status::PlannerStatus`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct PlannerReport {
    pub planner_id: String,
    pub protocol_version: u16,
    pub uptime_seconds: f64,
    pub runs: Vec<RunReport>,
    pub fleet: FleetReport,
    /// Stored runs the planner set aside (they could not be opened), with the reason.
    pub failed_runs: Vec<FailedRunReport>,
    /// Stored runs whose opening failed on an error that may pass, tried again with a backoff.
    pub retrying_runs: Vec<RetryingRunReport>,
    /// Stored runs left closed at a budget (the first ones by name), and how many there are.
    pub dormant_runs: Vec<DormantRunReport>,
    pub dormant_run_count: u64,
}

/// A stored run being tried again (a lenient mirror of `service::status::RetryingRun`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct RetryingRunReport {
    pub name: String,
    pub reason: String,
    pub attempts: u32,
    pub next_try_seconds: f64,
}

/// A stored run left closed at a budget (a lenient mirror of `service::status::DormantRun`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct DormantRunReport {
    pub name: String,
    /// The setting whose budget kept it closed.
    pub budget: String,
}

/// A stored run set aside (a lenient mirror of `service::status::FailedRun`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct FailedRunReport {
    pub name: String,
    pub reason: String,
}

/// The fleet as a planner sees it (a lenient mirror of `fleet::FleetStatus`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct FleetReport {
    pub planners: Vec<String>,
    pub pins: PinsReport,
    pub events: Vec<EventReport>,
    /// The planner's etcd lease (absent for a single daemon).
    pub lease: Option<LeaseReport>,
}

/// A fleet planner's etcd lease (a lenient mirror of `fleet::LeaseStatus`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct LeaseReport {
    pub valid_for_seconds: f64,
    pub ttl_seconds: f64,
    pub reachable: bool,
    pub failures: u64,
}

#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct PinsReport {
    pub serve: Vec<String>,
    pub refuse: Vec<String>,
}

/// One ownership event (a lenient mirror of `fleet::FleetEvent`: every field optional, so a
/// newer daemon's kinds still display).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct EventReport {
    pub at_unix_s: f64,
    pub event: String,
    pub run: Option<String>,
    pub epoch: Option<u64>,
    pub previous: Option<String>,
    pub planner: Option<String>,
    pub reason: Option<String>,
}

/// One run in a planner's report (a lenient mirror of `service::status::RunStatus`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct RunReport {
    pub name: String,
    pub task: String,
    pub method: String,
    /// `sync` or `async`; kept as text so a newer daemon's mode still displays.
    pub mode: String,
    pub episodes: u64,
    pub transitions: u64,
    pub models_version: u64,
    pub epoch: u64,
    pub training: bool,
    pub exploring: bool,
    /// `(agent, episode, return)`, oldest first.
    pub last_returns: Vec<(String, u32, f32)>,
    pub agents: Vec<String>,
    pub planning_latency: Option<LatencyReport>,
    pub last_retraining: Option<LastRetrainingReport>,
}

/// The part of a run's last retraining the table shows (a lenient mirror of
/// `run::stats::LastRetraining`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct LastRetrainingReport {
    pub termination_accuracy: Option<TerminationAccuracyReport>,
}

/// A learned termination's held-out accuracy (a lenient mirror of
/// `proto::TerminationAccuracy`).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct TerminationAccuracyReport {
    pub held_out: u32,
    pub terminations: u32,
    pub accuracy: f32,
    pub recall: f32,
}

#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(default)]
pub struct LatencyReport {
    pub p50_ms: f32,
    pub p90_ms: f32,
    pub p99_ms: f32,
    pub samples: u64,
}

/// Runs the subcommand: query, then print the table or the JSON.
pub fn run(args: StatusArgs) -> Result<()> {
    if args.connect.is_empty() && args.zenoh_config.is_none() {
        bail!(
            "say where the planners are: --connect ENDPOINT (a planner's --listen endpoint or a router), or --zenoh-config FILE"
        );
    }
    if let Some(id) = &args.planner {
        proto::validate_name(id)?;
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .context("tokio runtime")?;
    let replies = runtime.block_on(query(&args))?;
    if replies.is_empty() {
        let key = status_key(&args);
        bail!(
            "no planner answered on `{key}` within {} s: is it running, and does --connect reach it (or its router)?",
            args.timeout
        );
    }
    if args.json {
        let values: Vec<serde_json::Value> = replies.into_iter().map(|(_, v)| v).collect();
        println!("{}", serde_json::to_string_pretty(&values)?);
        return Ok(());
    }
    let mut reports = Vec::with_capacity(replies.len());
    for (key, value) in replies {
        let report: PlannerReport = serde_json::from_value(value)
            .with_context(|| format!("the status from `{key}` is not a planner report"))?;
        reports.push(report);
    }
    print!("{}", render(&reports));
    Ok(())
}

fn status_key(args: &StatusArgs) -> String {
    let keys = Keys::new(&args.prefix);
    match &args.planner {
        Some(id) => keys.planner_status(id),
        None => keys.all_planner_status(),
    }
}

/// Every planner's JSON report with the key it came from, sorted by planner id.
async fn query(args: &StatusArgs) -> Result<Vec<(String, serde_json::Value)>> {
    let base = match &args.zenoh_config {
        Some(path) => Some(
            zenoh::Config::from_file(path)
                .map_err(|e| anyhow::anyhow!("zenoh config {}: {e}", path.display()))?,
        ),
        None => None,
    };
    let endpoints = proto::session::Endpoints {
        listen: Vec::new(),
        connect: args.connect.clone(),
    };
    let mut config = proto::session::zenoh_config(&endpoints, base)?;
    config
        .insert_json5("mode", "\"client\"")
        .map_err(|e| anyhow::anyhow!("client mode: {e}"))?;
    let session = zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("opening the zenoh session: {e}"))?;
    let timeout = Duration::try_from_secs_f64(args.timeout)
        .with_context(|| format!("--timeout {}", args.timeout))?;
    let deadline = tokio::time::Instant::now() + timeout;
    let keys = Keys::new(&args.prefix);
    let expected = match &args.planner {
        Some(id) => BTreeSet::from([id.clone()]),
        None => live_planners(&session, &keys, timeout).await?,
    };
    let mut reports: BTreeMap<String, (String, serde_json::Value)> = BTreeMap::new();
    let mut key = status_key(args);
    loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        for (from, value) in ask(&session, &key, left).await? {
            reports.insert(planner_id(&value).to_string(), (from, value));
        }
        let missing: Vec<&String> = expected
            .iter()
            .filter(|id| !reports.contains_key(*id))
            .collect();
        let Some(next) = missing.first() else { break };
        if tokio::time::Instant::now() + RETRY_PAUSE >= deadline {
            let names: Vec<&str> = missing.iter().map(|s| s.as_str()).collect();
            eprintln!(
                "warning: planner{} {} {} alive but did not answer within {} s",
                if names.len() == 1 { "" } else { "s" },
                names.join(", "),
                if names.len() == 1 { "is" } else { "are" },
                args.timeout
            );
            break;
        }
        tokio::time::sleep(RETRY_PAUSE).await;
        key = keys.planner_status(next);
    }
    session
        .close()
        .await
        .map_err(|e| anyhow::anyhow!("closing the zenoh session: {e}"))?;
    Ok(reports.into_values().collect())
}

/// Pause before asking a planner again that is alive but did not answer.
const RETRY_PAUSE: Duration = Duration::from_millis(200);

/// The planners whose liveliness tokens the router knows.
async fn live_planners(
    session: &zenoh::Session,
    keys: &Keys,
    timeout: Duration,
) -> Result<BTreeSet<String>> {
    let replies = session
        .liveliness()
        .get(keys.all_planners_alive())
        .timeout(timeout)
        .await
        .map_err(|e| anyhow::anyhow!("reading the planners' liveliness: {e}"))?;
    let mut live = BTreeSet::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result()
            && let Some(id) = keys.parse_planner_alive(sample.key_expr().as_str())
        {
            live.insert(id.to_string());
        }
    }
    Ok(live)
}

/// One status query on `key` (a planner's or the wildcard): the JSON answers with their keys.
async fn ask(
    session: &zenoh::Session,
    key: &str,
    timeout: Duration,
) -> Result<Vec<(String, serde_json::Value)>> {
    // Every planner answers on the same wildcard query: no consolidation, or all but one of
    // their answers could be dropped as duplicates.
    let replies = session
        .get(key)
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .await
        .map_err(|e| anyhow::anyhow!("querying {key}: {e}"))?;
    let mut reports = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => {
                let from = sample.key_expr().to_string();
                let value: serde_json::Value = serde_json::from_slice(&sample.payload().to_bytes())
                    .with_context(|| format!("the status from `{from}` is not JSON"))?;
                reports.push((from, value));
            }
            Err(e) => tracing::warn!(
                %key,
                reason = %String::from_utf8_lossy(&e.payload().to_bytes()),
                "a status query failed"
            ),
        }
    }
    Ok(reports)
}

fn planner_id(value: &serde_json::Value) -> &str {
    value
        .get("planner_id")
        .and_then(serde_json::Value::as_str)
        .unwrap_or("")
}

/// The human-readable report: per planner a heading, its runs' table and its agents.
pub fn render(reports: &[PlannerReport]) -> String {
    let mut out = String::new();
    for (i, report) in reports.iter().enumerate() {
        if i > 0 {
            out.push('\n');
        }
        let _ = writeln!(
            out,
            "planner {} (protocol {}, up {}): {} run{}",
            report.planner_id,
            report.protocol_version,
            uptime(report.uptime_seconds),
            report.runs.len(),
            if report.runs.len() == 1 { "" } else { "s" },
        );
        render_fleet(&mut out, &report.fleet);
        render_failed(&mut out, &report.failed_runs);
        render_retrying(&mut out, &report.retrying_runs);
        render_dormant(&mut out, &report.dormant_runs, report.dormant_run_count);
        if report.runs.is_empty() {
            continue;
        }
        let rows: Vec<Vec<String>> = report.runs.iter().map(run_row).collect();
        out.push_str(&table(&COLUMNS, &rows));
        out.push_str("agents:\n");
        for run in &report.runs {
            let agents = if run.agents.is_empty() {
                "(none attached)".to_string()
            } else {
                run.agents.join(", ")
            };
            let _ = writeln!(out, "  {}: {agents}", run.name);
        }
        render_terminations(&mut out, &report.runs);
    }
    out
}

/// Stored runs whose opening is being tried again, one line each.
fn render_retrying(out: &mut String, retrying: &[RetryingRunReport]) {
    if retrying.is_empty() {
        return;
    }
    let _ = writeln!(out, "runs retrying to open (stored, not served yet):");
    for run in retrying {
        let _ = writeln!(
            out,
            "  {}: {} (failed {} time{}, next try in {:.0}s)",
            one_line(&run.name, FAILED_NAME_CHARS),
            one_line(&run.reason, FAILED_REASON_CHARS),
            run.attempts,
            if run.attempts == 1 { "" } else { "s" },
            run.next_try_seconds.max(0.0),
        );
    }
}

/// Most dormant runs the table names (the report itself names at most a hundred).
const DORMANT_SHOWN: usize = 10;

/// How many stored runs stay closed at a budget, and the first few with the budget's setting.
fn render_dormant(out: &mut String, dormant: &[DormantRunReport], count: u64) {
    let count = count.max(dormant.len() as u64);
    if count == 0 {
        return;
    }
    let _ = writeln!(
        out,
        "dormant runs (stored, closed at a budget, opened when it allows): {count}"
    );
    for run in dormant.iter().take(DORMANT_SHOWN) {
        let _ = writeln!(
            out,
            "  {}: {}",
            one_line(&run.name, FAILED_NAME_CHARS),
            one_line(&run.budget, FAILED_NAME_CHARS)
        );
    }
    let named = dormant.len().min(DORMANT_SHOWN) as u64;
    if count > named {
        let _ = writeln!(
            out,
            "  … and {} more (`--json` lists up to 100)",
            count - named
        );
    }
}

/// The held-out accuracy of each run's learned termination, for the runs that have one.
fn render_terminations(out: &mut String, runs: &[RunReport]) {
    let learned: Vec<(&str, &TerminationAccuracyReport)> = runs
        .iter()
        .filter_map(|run| {
            let accuracy = run
                .last_retraining
                .as_ref()?
                .termination_accuracy
                .as_ref()?;
            Some((run.name.as_str(), accuracy))
        })
        .collect();
    if learned.is_empty() {
        return;
    }
    out.push_str("learned terminations (held-out transitions of the last retraining):\n");
    for (name, t) in learned {
        let _ = writeln!(
            out,
            "  {name}: accuracy {:.3}, recall {:.3} ({} held out, {} ends)",
            t.accuracy, t.recall, t.held_out, t.terminations
        );
    }
}

/// Characters of a failed run's name and reason the table shows: both come from the disk and
/// from error messages, and one line per run keeps the table readable.
const FAILED_NAME_CHARS: usize = 40;
const FAILED_REASON_CHARS: usize = 160;

/// The stored runs the planner set aside, one line each, with the reason cut short safely
/// (at a character boundary, control characters shown as spaces).
fn render_failed(out: &mut String, failed: &[FailedRunReport]) {
    if failed.is_empty() {
        return;
    }
    let _ = writeln!(out, "failed runs (stored, set aside, not served):");
    for run in failed {
        let _ = writeln!(
            out,
            "  {}: {}",
            one_line(&run.name, FAILED_NAME_CHARS),
            one_line(&run.reason, FAILED_REASON_CHARS)
        );
    }
}

/// `text` on one line (control characters as spaces), cut to `max` characters with a `…`.
fn one_line(text: &str, max: usize) -> String {
    let mut shown: String = text
        .chars()
        .take(max)
        .map(|c| if c.is_control() { ' ' } else { c })
        .collect();
    if text.chars().count() > max {
        shown.push('…');
    }
    shown
}

/// How many of a planner's most recent ownership events the table shows.
const EVENTS_SHOWN: usize = 8;

/// The fleet line (only in a fleet or with pins: a lone planner's report stays as it was) and
/// the recent ownership events.
fn render_fleet(out: &mut String, fleet: &FleetReport) {
    let pinned = !fleet.pins.serve.is_empty() || !fleet.pins.refuse.is_empty();
    if fleet.planners.len() > 1 || pinned {
        let list = |l: &[String]| {
            if l.is_empty() {
                "-".to_string()
            } else {
                l.join(" ")
            }
        };
        let _ = writeln!(
            out,
            "fleet: {} planners ({}); serves {}; refuses {}",
            fleet.planners.len(),
            fleet.planners.join(", "),
            if fleet.pins.serve.is_empty() {
                "*".to_string()
            } else {
                list(&fleet.pins.serve)
            },
            list(&fleet.pins.refuse),
        );
    }
    if let Some(lease) = &fleet.lease {
        let _ = writeln!(
            out,
            "etcd lease: valid {:.1} s more (ttl {:.0} s); etcd {}; {} failures to reach it",
            lease.valid_for_seconds,
            lease.ttl_seconds,
            if lease.reachable {
                "reachable"
            } else {
                "UNREACHABLE"
            },
            lease.failures
        );
    }
    let events = &fleet.events[fleet.events.len().saturating_sub(EVENTS_SHOWN)..];
    let ownership: Vec<String> = events.iter().filter_map(describe_event).collect();
    if !ownership.is_empty() {
        out.push_str("ownership events:\n");
        for line in ownership {
            let _ = writeln!(out, "  {line}");
        }
    }
}

/// One event as a line: when (UTC time of day) and what.
fn describe_event(e: &EventReport) -> Option<String> {
    let secs = e.at_unix_s.max(0.0) as u64 % 86400;
    let at = format!("{:02}:{:02}:{:02}", secs / 3600, secs / 60 % 60, secs % 60);
    let run = e.run.as_deref().unwrap_or("?");
    let epoch = e.epoch.map_or_else(|| "?".to_string(), |n| n.to_string());
    let what = match e.event.as_str() {
        "took" => match &e.previous {
            Some(previous) => format!("took {run} at epoch {epoch} (from {previous})"),
            None => format!("took {run} at epoch {epoch}"),
        },
        "stepped_down" => format!(
            "stepped down from {run} (epoch {epoch}): {}",
            e.reason.as_deref().unwrap_or("?")
        ),
        "planner_joined" => format!("planner {} joined", e.planner.as_deref()?),
        "planner_left" => format!("planner {} left", e.planner.as_deref()?),
        other => other.to_string(),
    };
    Some(format!("{at} {what}"))
}

/// A column: its heading and whether its cells are numbers (right-aligned).
struct Column {
    heading: &'static str,
    numeric: bool,
}

const fn col(heading: &'static str, numeric: bool) -> Column {
    Column { heading, numeric }
}

const COLUMNS: [Column; 12] = [
    col("RUN", false),
    col("TASK", false),
    col("PRESET", false),
    col("MODE", false),
    col("EPISODES", true),
    col("TRANSITIONS", true),
    col("STATE", false),
    col("MODELS", true),
    col("EPOCH", true),
    col("AGENTS", true),
    col("LAST RETURNS", false),
    col("PLAN MS p50/p90/p99", false),
];

fn run_row(run: &RunReport) -> Vec<String> {
    vec![
        run.name.clone(),
        run.task.clone(),
        run.method.clone(),
        run.mode.clone(),
        run.episodes.to_string(),
        run.transitions.to_string(),
        state(run),
        format!("v{}", run.models_version),
        run.epoch.to_string(),
        run.agents.len().to_string(),
        last_returns(&run.last_returns),
        latency(run.planning_latency.as_ref()),
    ]
}

/// What the run is doing: retraining and/or still acting randomly, or planning with its models.
fn state(run: &RunReport) -> String {
    match (run.training, run.exploring) {
        (true, true) => "training, exploring".into(),
        (true, false) => "training".into(),
        (false, true) => "exploring".into(),
        (false, false) => "planning".into(),
    }
}

/// The most recent returns, oldest first, so the trend reads left to right.
fn last_returns(returns: &[(String, u32, f32)]) -> String {
    if returns.is_empty() {
        return "-".into();
    }
    let recent = &returns[returns.len().saturating_sub(RETURNS_SHOWN)..];
    recent
        .iter()
        .map(|(_, _, r)| format!("{r:.2}"))
        .collect::<Vec<_>>()
        .join(" ")
}

fn latency(latency: Option<&LatencyReport>) -> String {
    match latency {
        None => "-".into(),
        Some(l) => format!(
            "{:.1}/{:.1}/{:.1} (n={})",
            l.p50_ms, l.p90_ms, l.p99_ms, l.samples
        ),
    }
}

fn uptime(seconds: f64) -> String {
    let s = seconds.max(0.0) as u64;
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        3600..86400 => format!("{}h{:02}m", s / 3600, s % 3600 / 60),
        _ => format!("{}d{:02}h", s / 86400, s % 86400 / 3600),
    }
}

/// Left-aligned text and right-aligned numbers, columns two spaces apart, no trailing blanks.
fn table(columns: &[Column], rows: &[Vec<String>]) -> String {
    let widths: Vec<usize> = columns
        .iter()
        .enumerate()
        .map(|(i, c)| {
            rows.iter()
                .map(|r| r[i].chars().count())
                .chain([c.heading.chars().count()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    let line = |cells: Vec<&str>| {
        let mut text = String::new();
        for (i, (cell, column)) in cells.iter().zip(columns).enumerate() {
            if i > 0 {
                text.push_str("  ");
            }
            let pad = widths[i] - cell.chars().count();
            if column.numeric {
                text.push_str(&" ".repeat(pad));
                text.push_str(cell);
            } else {
                text.push_str(cell);
                text.push_str(&" ".repeat(pad));
            }
        }
        text.truncate(text.trim_end().len());
        text.push('\n');
        text
    };
    let mut out = line(columns.iter().map(|c| c.heading).collect());
    for row in rows {
        out.push_str(&line(row.iter().map(String::as_str).collect()));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A report as `service::status` serialises it (two runs, one without latencies yet), plus
    /// a field this client does not know.
    const FIXTURE: &str = r#"{
        "planner_id": "lab-1",
        "protocol_version": 2,
        "uptime_seconds": 3725.4,
        "some_future_field": {"x": 1},
        "fleet": {
            "planners": ["lab-1", "lab-2"],
            "pins": {"serve": [], "refuse": ["gpu-*"]},
            "events": [
                {"at_unix_s": 3661.5, "event": "planner_joined", "planner": "lab-2"},
                {"at_unix_s": 3700.0, "event": "took", "run": "cartpole-deen", "epoch": 3, "previous": "lab-2"},
                {"at_unix_s": 3710.0, "event": "stepped_down", "run": "ant-2", "epoch": 4, "reason": "lab-2 holds it at epoch 5"},
                {"at_unix_s": 3720.0, "event": "some_future_event", "run": "x"}
            ]
        },
        "runs": [
            {
                "name": "cartpole-deen",
                "task": "cartpole",
                "method": "cem+deen",
                "mode": "sync",
                "episodes": 7,
                "transitions": 1400,
                "models_version": 6,
                "epoch": 3,
                "training": true,
                "exploring": false,
                "last_returns": [["bridge-0", 0, 1.5], ["bridge-0", 1, 2.25], ["bridge-1", 0, 3.0],
                                 ["bridge-0", 2, 10.125], ["bridge-1", 1, 48.0],
                                 ["bridge-0", 3, 97.5], ["bridge-1", 2, 120.0]],
                "agents": ["bridge-0", "bridge-1"],
                "planning_latency": {"p50_ms": 12.25, "p90_ms": 20.0, "p99_ms": 31.5, "samples": 1000}
            },
            {
                "name": "ant-1",
                "task": "ant",
                "method": "pets",
                "mode": "async",
                "episodes": 0,
                "transitions": 40,
                "models_version": 0,
                "epoch": 1,
                "training": false,
                "exploring": true,
                "last_returns": [],
                "agents": [],
                "planning_latency": null
            }
        ]
    }"#;

    fn fixture() -> PlannerReport {
        serde_json::from_str(FIXTURE).unwrap()
    }

    #[test]
    fn reads_the_daemons_report() {
        let report = fixture();
        assert_eq!(report.planner_id, "lab-1");
        assert_eq!(report.runs.len(), 2);
        let run = &report.runs[0];
        assert_eq!((run.episodes, run.transitions), (7, 1400));
        assert_eq!(run.last_returns[6], ("bridge-1".to_string(), 2, 120.0));
        assert_eq!(run.planning_latency.as_ref().unwrap().samples, 1000);
        assert_eq!(report.runs[1].planning_latency, None);
    }

    #[test]
    fn renders_the_table() {
        let expected = "\
planner lab-1 (protocol 2, up 1h02m): 2 runs
fleet: 2 planners (lab-1, lab-2); serves *; refuses gpu-*
ownership events:
  01:01:01 planner lab-2 joined
  01:01:40 took cartpole-deen at epoch 3 (from lab-2)
  01:01:50 stepped down from ant-2 (epoch 4): lab-2 holds it at epoch 5
  01:02:00 some_future_event
RUN            TASK      PRESET    MODE   EPISODES  TRANSITIONS  STATE      MODELS  EPOCH  AGENTS  LAST RETURNS                   PLAN MS p50/p90/p99
cartpole-deen  cartpole  cem+deen  sync          7         1400  training       v6      3       2  3.00 10.12 48.00 97.50 120.00  12.2/20.0/31.5 (n=1000)
ant-1          ant       pets      async         0           40  exploring      v0      1       0  -                              -
agents:
  cartpole-deen: bridge-0, bridge-1
  ant-1: (none attached)
";
        assert_eq!(render(&[fixture()]), expected);
    }

    #[test]
    fn failed_runs_are_listed_with_their_reason_cut_short() {
        let long = format!("cannot open: {}\nsecond line", "x".repeat(500));
        let report = PlannerReport {
            planner_id: "p".into(),
            protocol_version: 3,
            failed_runs: vec![
                FailedRunReport {
                    name: "old-run".into(),
                    reason: "dynamics_hidden_size = 4000000000 is over the limit".into(),
                },
                FailedRunReport {
                    name: "é".repeat(100),
                    reason: long,
                },
            ],
            ..PlannerReport::default()
        };
        let text = render(&[report]);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[1], "failed runs (stored, set aside, not served):");
        assert_eq!(
            lines[2],
            "  old-run: dynamics_hidden_size = 4000000000 is over the limit"
        );
        let expected_reason = format!("cannot open: {}…", "x".repeat(FAILED_REASON_CHARS - 13));
        assert_eq!(
            lines[3],
            format!("  {}…: {expected_reason}", "é".repeat(FAILED_NAME_CHARS))
        );
        assert_eq!(lines.len(), 4, "{text}");
        // The daemon's JSON field is read.
        let json = r#"{"planner_id":"p","failed_runs":[{"name":"r","reason":"why"}]}"#;
        let read: PlannerReport = serde_json::from_str(json).unwrap();
        assert_eq!(read.failed_runs[0].reason, "why");
    }

    #[test]
    fn planners_without_runs_and_several_planners() {
        let idle = PlannerReport {
            planner_id: "idle".into(),
            protocol_version: 1,
            uptime_seconds: 59.9,
            runs: Vec::new(),
            ..PlannerReport::default()
        };
        let text = render(&[idle.clone(), fixture()]);
        assert!(
            text.starts_with("planner idle (protocol 1, up 59s): 0 runs\n\nplanner lab-1"),
            "{text}"
        );
        assert_eq!(text.matches("RUN ").count(), 1, "{text}");
    }

    #[test]
    fn missing_fields_take_defaults() {
        let report: PlannerReport =
            serde_json::from_str(r#"{"planner_id": "p", "runs": [{"name": "r"}]}"#).unwrap();
        let text = render(&[report]);
        assert!(text.contains("\nr  "), "{text}");
        assert!(text.contains("planning"), "{text}");
    }

    #[test]
    fn retrying_and_dormant_runs_and_learned_terminations_are_shown() {
        let json = r#"{
            "planner_id": "p",
            "protocol_version": 6,
            "retrying_runs": [{"name": "r1", "reason": "disk busy", "attempts": 2, "next_try_seconds": 3.6}],
            "dormant_runs": [{"name": "old-1", "budget": "max_runs"}, {"name": "old-2", "budget": "max_runs"}],
            "dormant_run_count": 13,
            "runs": [
                {"name": "pendulum", "last_retraining": {"models_version": 3, "seconds": 1.5,
                    "termination_accuracy": {"held_out": 57, "terminations": 4, "accuracy": 0.982, "recall": 1.0}}},
                {"name": "cart", "last_retraining": {"models_version": 2, "seconds": 0.5}}
            ]
        }"#;
        let report: PlannerReport = serde_json::from_str(json).unwrap();
        let text = render(&[report]);
        for line in [
            "runs retrying to open (stored, not served yet):",
            "  r1: disk busy (failed 2 times, next try in 4s)",
            "dormant runs (stored, closed at a budget, opened when it allows): 13",
            "  old-1: max_runs",
            "  … and 11 more (`--json` lists up to 100)",
            "learned terminations (held-out transitions of the last retraining):",
            "  pendulum: accuracy 0.982, recall 1.000 (57 held out, 4 ends)",
        ] {
            assert!(
                text.lines().any(|l| l == line),
                "no line {line:?} in:\n{text}"
            );
        }
        assert!(!text.contains("  cart: accuracy"), "{text}");
        // Nothing of these in a report without them.
        let plain = render(&[fixture()]);
        assert!(
            !plain.contains("dormant") && !plain.contains("retrying") && !plain.contains("learned")
        );
    }

    #[test]
    fn uptime_units() {
        assert_eq!(uptime(0.4), "0s");
        assert_eq!(uptime(61.0), "1m01s");
        assert_eq!(uptime(3600.0 * 5.0 + 60.0 * 7.0), "5h07m");
        assert_eq!(uptime(86400.0 * 3.0 + 3600.0 * 2.0), "3d02h");
    }
}
