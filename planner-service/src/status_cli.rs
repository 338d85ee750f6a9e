//! `planner-service status`: asks running planners for their status and prints it as a table
//! (or as the raw JSON with `--json`).
//!
//! The daemon's side of this exchange is `service/status.rs`: every planner serves a JSON report
//! on `{prefix}/planners/{id}/status`. This client queries one planner or, by default, all of
//! them with a wildcard, through the same explicit endpoints (or router) the agents use.
//!
//! The report is read into this module's own lenient mirror of the daemon's types: unknown
//! fields are ignored and missing ones take defaults, so an operator's `status` keeps working
//! against a planner of another release instead of refusing the whole report.

use anyhow::{Context, Result, bail};
use proto::Keys;
use serde::Deserialize;
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
    pub training: bool,
    pub exploring: bool,
    /// `(agent, episode, return)`, oldest first.
    pub last_returns: Vec<(String, u32, f32)>,
    pub agents: Vec<String>,
    pub planning_latency: Option<LatencyReport>,
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
    let config = proto::session::zenoh_config(&endpoints, base)?;
    let session = zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("opening the zenoh session: {e}"))?;
    let key = status_key(args);
    let timeout = Duration::try_from_secs_f64(args.timeout)
        .with_context(|| format!("--timeout {}", args.timeout))?;
    // Every planner answers on the same wildcard query: no consolidation, or all but one of
    // their answers could be dropped as duplicates.
    let replies = session
        .get(&key)
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
    session
        .close()
        .await
        .map_err(|e| anyhow::anyhow!("closing the zenoh session: {e}"))?;
    reports.sort_by(|a, b| planner_id(&a.1).cmp(planner_id(&b.1)));
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
    }
    out
}

/// A column: its heading and whether its cells are numbers (right-aligned).
struct Column {
    heading: &'static str,
    numeric: bool,
}

const fn col(heading: &'static str, numeric: bool) -> Column {
    Column { heading, numeric }
}

const COLUMNS: [Column; 11] = [
    col("RUN", false),
    col("TASK", false),
    col("PRESET", false),
    col("MODE", false),
    col("EPISODES", true),
    col("TRANSITIONS", true),
    col("STATE", false),
    col("MODELS", true),
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
        "protocol_version": 1,
        "uptime_seconds": 3725.4,
        "some_future_field": {"x": 1},
        "runs": [
            {
                "name": "cartpole-deen",
                "task": "cartpole",
                "method": "cem+deen",
                "mode": "sync",
                "episodes": 7,
                "transitions": 1400,
                "models_version": 6,
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
planner lab-1 (protocol 1, up 1h02m): 2 runs
RUN            TASK      PRESET    MODE   EPISODES  TRANSITIONS  STATE      MODELS  AGENTS  LAST RETURNS                   PLAN MS p50/p90/p99
cartpole-deen  cartpole  cem+deen  sync          7         1400  training       v6       2  3.00 10.12 48.00 97.50 120.00  12.2/20.0/31.5 (n=1000)
ant-1          ant       pets      async         0           40  exploring      v0       0  -                              -
agents:
  cartpole-deen: bridge-0, bridge-1
  ant-1: (none attached)
";
        assert_eq!(render(&[fixture()]), expected);
    }

    #[test]
    fn planners_without_runs_and_several_planners() {
        let idle = PlannerReport {
            planner_id: "idle".into(),
            protocol_version: 1,
            uptime_seconds: 59.9,
            runs: Vec::new(),
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
    fn uptime_units() {
        assert_eq!(uptime(0.4), "0s");
        assert_eq!(uptime(61.0), "1m01s");
        assert_eq!(uptime(3600.0 * 5.0 + 60.0 * 7.0), "5h07m");
        assert_eq!(uptime(86400.0 * 3.0 + 3600.0 * 2.0), "3d02h");
    }
}
