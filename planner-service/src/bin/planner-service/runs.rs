//! `planner-service runs list|delete|archive`: the runs stored in a data directory.
//!
//! These work on the files directly. Deleting and archiving take the data directory's lock
//! (see `persist::admin`), so they are refused while a daemon serves the directory: stop the
//! daemon, change the runs, start it again. Listing only reads and works at any time.

use anyhow::Result;
use planner_service::config::ServiceConfig;
use planner_service::persist::admin;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
pub struct RunsArgs {
    /// The daemon's TOML configuration, to take its data directory from.
    #[arg(long, env = "EBMPC_CONFIG", global = true)]
    config: Option<PathBuf>,
    /// The data directory (overrides the configuration's; default: the daemon's default).
    #[arg(long, env = "EBMPC_DATA_DIR", global = true)]
    data_dir: Option<PathBuf>,
    #[command(subcommand)]
    command: RunsCommand,
}

#[derive(clap::Subcommand, Debug)]
enum RunsCommand {
    /// List the stored runs: task, preset, mode, replay log size, checkpoints.
    List,
    /// Delete a run and everything it stored (refused while a daemon serves the directory).
    Delete {
        /// The run's name.
        run: String,
    },
    /// Move a run to `{data_dir}/archive/{run}`, kept whole but no longer served (refused
    /// while a daemon serves the directory).
    Archive {
        /// The run's name.
        run: String,
    },
}

pub fn run(args: RunsArgs) -> Result<()> {
    let data_dir = match (args.data_dir, &args.config) {
        (Some(dir), _) => dir,
        (None, Some(path)) => ServiceConfig::load(path)?.data_dir,
        (None, None) => ServiceConfig::default().data_dir,
    };
    match args.command {
        RunsCommand::List => {
            println!(
                "{:<24} {:<12} {:<10} {:<6} {:>14} {:>12}",
                "run", "task", "preset", "mode", "replay bytes", "checkpoints"
            );
            for entry in admin::list_runs(&data_dir)? {
                let (task, preset, mode) = match &entry.spec {
                    Some(spec) => (
                        spec.task.to_string(),
                        spec.preset.clone().unwrap_or_else(|| "default".into()),
                        format!("{:?}", spec.mode).to_lowercase(),
                    ),
                    None => ("?".into(), "?".into(), "?".into()),
                };
                println!(
                    "{:<24} {:<12} {:<10} {:<6} {:>14} {:>12}",
                    entry.name, task, preset, mode, entry.replay_bytes, entry.checkpoints
                );
            }
        }
        RunsCommand::Delete { run } => {
            admin::delete_run(&data_dir, &run)?;
            println!("deleted run `{run}` from {}", data_dir.display());
        }
        RunsCommand::Archive { run } => {
            let to = admin::archive_run(&data_dir, &run)?;
            println!("archived run `{run}` to {}", to.display());
        }
    }
    Ok(())
}
