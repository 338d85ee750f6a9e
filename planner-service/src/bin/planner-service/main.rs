//! `planner-service`: the ebmpc planner daemon and its tools.

mod bench;
mod runs;
mod status;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use planner_service::config::ServiceConfig;
use planner_service::service::Service;
use std::path::PathBuf;
use tracing_subscriber::EnvFilter;

/// The ebmpc planner: learns dynamics and energy models from agents' experience and answers
/// every observation with a model-predictive action (CEM regularised by DEEN energy).
#[derive(Parser, Debug)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the planner daemon: serve attach requests and observations over Zenoh until
    /// SIGINT/SIGTERM.
    Serve(ServeArgs),
    /// Measure planning and training speed at a preset's sizes.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Ask running planners for their runs, agents and planning latencies (a table, or --json).
    Status(status::StatusArgs),
    /// List, delete or archive the runs stored in a data directory.
    Runs(runs::RunsArgs),
}

#[derive(clap::Args, Debug)]
struct ServeArgs {
    /// TOML configuration file (see deploy/planner.toml); flags below override its values.
    #[arg(long, env = "EBMPC_CONFIG")]
    config: Option<PathBuf>,
    /// Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable).
    #[arg(long, env = "EBMPC_LISTEN", value_delimiter = ',')]
    listen: Vec<String>,
    /// Zenoh endpoint (a peer or a zenohd router) to connect to (repeatable).
    #[arg(long, env = "EBMPC_CONNECT", value_delimiter = ',')]
    connect: Vec<String>,
    /// A zenoh configuration file (JSON5) to start from, e.g. deploy/zenoh-client.json5; the
    /// endpoints above are applied on top.
    #[arg(long, env = "EBMPC_ZENOH_CONFIG")]
    zenoh_config: Option<PathBuf>,
    /// This planner's id (its status key and liveliness token).
    #[arg(long, env = "EBMPC_PLANNER_ID")]
    planner_id: Option<String>,
    /// Key prefix shared with the agents.
    #[arg(long, env = "EBMPC_PREFIX")]
    prefix: Option<String>,
    /// Directory for replay buffers and models (default: `var/ebmpc`, relative to the
    /// working directory).
    #[arg(long, env = "EBMPC_DATA_DIR")]
    data_dir: Option<PathBuf>,
    /// Stop (as on SIGTERM) when standard input reaches its end. A parent that starts the
    /// daemon with a pipe on its standard input and keeps the write end open keeps the daemon
    /// no longer than itself: the kernel closes that end when the parent exits, also when it
    /// is killed with SIGKILL (the Python package's `Planner.local` does this).
    #[arg(long)]
    exit_on_stdin_close: bool,
    /// A folder of task specs, one `NAME.toml` or `NAME.json` file each, that this planner
    /// knows besides the built-in tasks (e.g. examples/tasks).
    #[arg(long, env = "EBMPC_TASKS_DIR")]
    tasks_dir: Option<PathBuf>,
}

impl ServeArgs {
    fn into_config(self) -> Result<ServiceConfig> {
        let mut config = match &self.config {
            Some(path) => ServiceConfig::load(path)?,
            None => ServiceConfig::default(),
        };
        if !self.listen.is_empty() {
            config.listen = self.listen;
        }
        if !self.connect.is_empty() {
            config.connect = self.connect;
        }
        if let Some(path) = self.zenoh_config {
            config.zenoh_config = Some(path);
        }
        if let Some(id) = self.planner_id {
            config.planner_id = id;
        }
        if let Some(prefix) = self.prefix {
            config.prefix = prefix;
        }
        if let Some(dir) = self.data_dir {
            config.data_dir = dir;
        }
        if let Some(dir) = self.tasks_dir {
            config.tasks_dir = Some(dir);
        }
        config.validate()?;
        Ok(config)
    }
}

/// How long blocking work (a plan in progress) may delay the exit after the service stopped.
const SHUTDOWN_BLOCKING_GRACE: std::time::Duration = std::time::Duration::from_secs(2);

/// Resolves when the process is asked to stop (SIGINT or SIGTERM), or, with
/// `exit_on_stdin_close`, when standard input reaches its end.
async fn shutdown_signal(exit_on_stdin_close: bool) {
    let signal = async {
        match proto::shutdown::shutdown_signal().await {
            Ok(signal) => tracing::info!("{signal} received"),
            Err(e) => {
                tracing::error!(error = %e, "cannot listen for stop signals; stop with SIGKILL");
                std::future::pending::<()>().await;
            }
        }
    };
    let stdin_closed = async {
        if exit_on_stdin_close {
            stdin_closed().await;
            tracing::info!("standard input closed: the parent process is gone");
        } else {
            std::future::pending::<()>().await;
        }
    };
    tokio::select! {
        () = signal => {}
        () = stdin_closed => {}
    }
}

/// Resolves once standard input reaches its end (or cannot be read): the process that held
/// the write end of its pipe closed it or died. Whatever is written is read and dropped. The
/// blocking read runs on a thread of its own, which the process's exit ends.
async fn stdin_closed() {
    let (closed, on_close) = tokio::sync::oneshot::channel::<()>();
    let spawned = std::thread::Builder::new()
        .name("stdin-watch".into())
        .spawn(move || {
            let mut buf = [0u8; 256];
            let mut stdin = std::io::stdin().lock();
            loop {
                match std::io::Read::read(&mut stdin, &mut buf) {
                    Ok(0) => break,
                    Err(e) if e.kind() != std::io::ErrorKind::Interrupted => break,
                    Ok(_) | Err(_) => {}
                }
            }
            let _ = closed.send(());
        });
    if let Err(e) = spawned {
        tracing::error!(error = %e, "cannot watch standard input; stop with SIGTERM");
        std::future::pending::<()>().await;
    }
    // A dropped sender (the thread ended) means the same as a sent value.
    let _ = on_close.await;
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info,zenoh=warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match cli.command {
        Command::Serve(args) => {
            let exit_on_stdin_close = args.exit_on_stdin_close;
            let config = args.into_config()?;
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()
                .context("tokio runtime")?;
            let served =
                runtime.block_on(Service::serve(config, shutdown_signal(exit_on_stdin_close)));
            // A plan still running on the blocking pool (its worker was abandoned) must not
            // hold the exit: the replay logs are already synced.
            runtime.shutdown_timeout(SHUTDOWN_BLOCKING_GRACE);
            served.context("planner service")?;
            Ok(())
        }
        Command::Bench(cmd) => {
            let report = bench::run(&cmd)?;
            println!("{report}");
            Ok(())
        }
        Command::Status(args) => status::run(args),
        Command::Runs(args) => runs::run(args),
    }
}
