//! `planner-service runs list|export|delete|archive`: the runs stored in a data directory.
//!
//! These work on the files directly. Deleting and archiving take the data directory's lock
//! (see `persist::admin`), so they are refused while a daemon serves the directory: stop the
//! daemon, change the runs, start it again. Listing and exporting only read and work at any time.

use anyhow::{Context, Result};
use planner_service::config::ServiceConfig;
use planner_service::persist::admin;
use planner_service::replay::{
    ActionOrigin, EpisodeEndRecord, HeaderRecord, Record, TransitionRecord,
};
use std::io::Write;
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
    List {
        /// List the archived runs (`{data_dir}/archive/`) instead of the served ones.
        #[arg(long)]
        archived: bool,
    },
    /// Write a run's stored transitions (or, with --episodes, its finished episodes) as CSV:
    /// one row per transition with the agent, episode, step, whether the action was the one
    /// planned or one the agent applied, the reward, then obs_*, act_* and next_obs_* columns.
    /// Reads only, so it works while a daemon serves the run.
    Export {
        /// The run's name.
        run: String,
        /// One row per finished episode instead: agent, episode, steps, return, how it ended.
        #[arg(long)]
        episodes: bool,
        /// Write to this file instead of standard output.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Read the run from the archive (`{data_dir}/archive/`) instead of the served runs.
        #[arg(long)]
        archived: bool,
    },
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
        RunsCommand::List { archived } => {
            println!(
                "{:<24} {:<12} {:<10} {:<6} {:>14} {:>12}",
                "run", "task", "preset", "mode", "replay bytes", "checkpoints"
            );
            for entry in admin::list_runs(&data_dir, shelf(archived))? {
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
        RunsCommand::Export {
            run,
            episodes,
            out,
            archived,
        } => {
            let recovered = admin::read_replay(&data_dir, shelf(archived), &run)?;
            let mut sink: Box<dyn Write> = match &out {
                Some(path) => Box::new(std::io::BufWriter::new(
                    std::fs::File::create(path)
                        .with_context(|| format!("cannot create {}", path.display()))?,
                )),
                None => Box::new(std::io::BufWriter::new(std::io::stdout().lock())),
            };
            let rows = if episodes {
                write_episodes(&mut sink, &recovered.records)?
            } else {
                write_transitions(&mut sink, &recovered.records)?
            };
            sink.flush()?;
            if recovered.damaged_regions > 0 || recovered.truncated_bytes > 0 {
                eprintln!(
                    "note: {} damaged stretch(es) ({} bytes) and a {}-byte unfinished tail were skipped",
                    recovered.damaged_regions, recovered.damaged_bytes, recovered.truncated_bytes
                );
            }
            if let Some(path) = out {
                println!("wrote {rows} rows of run `{run}` to {}", path.display());
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

fn shelf(archived: bool) -> admin::Shelf {
    if archived {
        admin::Shelf::Archived
    } else {
        admin::Shelf::Served
    }
}

/// The transitions of `records` as CSV rows (the header's state and action widths are those
/// of the log's header record). Returns the number of rows.
fn write_transitions(out: &mut dyn Write, records: &[Record]) -> Result<usize> {
    let (obs_dim, act_dim) = records
        .iter()
        .find_map(|r| match r {
            Record::Header(HeaderRecord {
                obs_dim, act_dim, ..
            }) => Some((*obs_dim as usize, *act_dim as usize)),
            _ => None,
        })
        .unwrap_or((0, 0));
    let mut header = vec!["agent", "episode", "step", "origin", "reward"]
        .into_iter()
        .map(String::from)
        .collect::<Vec<_>>();
    header.extend((0..obs_dim).map(|i| format!("obs_{i}")));
    header.extend((0..act_dim).map(|i| format!("act_{i}")));
    header.extend((0..obs_dim).map(|i| format!("next_obs_{i}")));
    writeln!(out, "{}", header.join(","))?;
    let mut rows = 0;
    for record in records {
        let Record::Transition(TransitionRecord {
            agent,
            episode,
            step,
            obs,
            act,
            origin,
            next_obs,
            reward,
            ..
        }) = record
        else {
            continue;
        };
        let origin = match origin {
            ActionOrigin::Planned => "planned",
            ActionOrigin::Applied => "applied",
        };
        write!(out, "{agent},{episode},{step},{origin},{reward}")?;
        for v in obs.iter().chain(act).chain(next_obs) {
            write!(out, ",{v}")?;
        }
        writeln!(out)?;
        rows += 1;
    }
    Ok(rows)
}

/// The finished episodes of `records` as CSV rows. Returns the number of rows.
fn write_episodes(out: &mut dyn Write, records: &[Record]) -> Result<usize> {
    writeln!(out, "agent,episode,steps,return,end")?;
    let mut rows = 0;
    for record in records {
        if let Record::EpisodeEnd(EpisodeEndRecord {
            agent,
            episode,
            steps,
            episode_return,
            end,
            ..
        }) = record
        {
            let end = match end {
                proto::EpisodeEnd::Terminated => "terminated",
                proto::EpisodeEnd::TimeLimit => "time_limit",
                proto::EpisodeEnd::Interrupted => "interrupted",
            };
            writeln!(out, "{agent},{episode},{steps},{episode_return},{end}")?;
            rows += 1;
        }
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transitions_and_episodes_are_written_as_csv() {
        let records = vec![
            Record::Header(HeaderRecord {
                task: "t".into(),
                obs_dim: 2,
                act_dim: 1,
            }),
            Record::Transition(TransitionRecord {
                epoch: 1,
                agent: "bridge-0".into(),
                episode: 3,
                step: 7,
                obs: vec![0.5, -1.0],
                act: vec![0.25],
                origin: ActionOrigin::Applied,
                next_obs: vec![0.75, 2.0],
                reward: -1.5,
            }),
            Record::EpisodeEnd(EpisodeEndRecord {
                epoch: 1,
                agent: "bridge-0".into(),
                episode: 3,
                steps: 8,
                episode_return: 12.5,
                end: proto::EpisodeEnd::Terminated,
            }),
        ];
        let mut out = Vec::new();
        assert_eq!(write_transitions(&mut out, &records).unwrap(), 1);
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "agent,episode,step,origin,reward,obs_0,obs_1,act_0,next_obs_0,next_obs_1\n\
             bridge-0,3,7,applied,-1.5,0.5,-1,0.25,0.75,2\n"
        );
        let mut out = Vec::new();
        assert_eq!(write_episodes(&mut out, &records).unwrap(), 1);
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "agent,episode,steps,return,end\nbridge-0,3,8,12.5,terminated\n"
        );
    }
}
