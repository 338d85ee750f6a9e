//! The `ebmpc-experiment` binary end to end: `plot` on a fixture, and `experiment` with stand-in
//! planner and bridge programs (shell scripts that behave like the real binaries at their
//! interface: the daemon logs "planner serving", a bridge writes its --out CSV row by row), so
//! launching, the CSV schema and resuming are checked in seconds and deterministically.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;

fn exe() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ebmpc-experiment"))
}

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("ebmpc-experiment-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn plot_renders_png_and_svg_from_a_fixture() {
    let dir = temp_dir("plot");
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/episodes.csv");
    std::fs::copy(&fixture, dir.join("episodes.csv")).unwrap();
    let out = exe().arg("plot").arg(&dir).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let png = std::fs::read(dir.join("learning_curves.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    assert!(png.len() > 5_000, "{} bytes", png.len());
    let svg = std::fs::read_to_string(dir.join("learning_curves.svg")).unwrap();
    assert!(svg.starts_with("<svg"), "{}", &svg[..svg.len().min(80)]);
    // Two methods: two bands (polygons) and two mean lines.
    assert!(svg.matches("<polygon").count() >= 2, "{svg}");
    assert!(svg.matches("<polyline").count() >= 2, "{svg}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Writes an executable shell script.
fn script(path: &Path, body: &str) {
    std::fs::write(path, format!("#!/bin/sh\n{body}")).unwrap();
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).unwrap();
}

/// Stand-ins for `planner-service` and `sim-bridge` in `dir`. The bridge appends its command
/// line to `calls.log` and writes `--episodes` rows of sim-bridge's CSV format, numbered on
/// from the episodes its `--run` already has (as the daemon's stored run numbers them: a file
/// per run name stands for the daemon's replay). With FAIL_SEED=<seed> in its environment it
/// fails after one episode for that seed; with HANG_SEED=<seed> it writes one episode for that
/// seed, records its pid in `hung.pid` and hangs (a run in progress, for killing the
/// launcher); with SLOW_SEED=<seed> it waits 5 s after each of that seed's episodes (a
/// retraining) and, stopped there, writes how many episodes it had finished to `stopped-after`.
/// WALL sets the wall seconds its rows report. Given `--deadline`, it applies the real bridge's
/// rule (the next episode takes as long as the last) after each episode and, stopping, also
/// writes `stopped-after`.
///
/// The planner appends its `serve` command line to `planner-calls.log` and its pid to
/// `planner.pid`; its `status --json` lists every run the bridges have written to, each with the
/// kernel paths a daemon on an AMX machine would report.
fn fake_binaries(dir: &Path) {
    let status = r#"if [ "$1" = status ]; then
  printf '[{"planner_id":"p","runs":['
  sep=''
  for f in DIR/daemon-*; do
    [ -e "$f" ] || continue
    printf '%s{"name":"%s","kernels":{"precision":"auto","dynamics":"amx-bf16","energy":"avx512-f32","reward":null}}' "$sep" "${f##*/daemon-}"
    sep=','
  done
  echo ']}]'
  exit 0
fi
"#
    .replace("DIR", &dir.display().to_string());
    script(
        &dir.join("planner-service"),
        &format!(
            "{status}echo \"$@\" >> {}\necho $$ > {}\necho 'INFO planner serving'\nexec sleep 300\n",
            dir.join("planner-calls.log").display(),
            dir.join("planner.pid").display()
        ),
    );
    let calls = dir.join("calls.log");
    script(
        &dir.join("sim-bridge"),
        &format!(
            r#"echo "$@" >> {calls}
while [ $# -gt 0 ]; do
  case "$1" in
    --out) out="$2"; shift;;
    --episodes) episodes="$2"; shift;;
    --seed) seed="$2"; shift;;
    --run) run="$2"; shift;;
    --deadline) deadline="$2"; shift;;
  esac
  shift
done
state="{dir}/daemon-$run"
e=$(cat "$state" 2>/dev/null || echo 0)
last=$((e + episodes))
echo "episode,return,steps,wall_seconds,planned_steps,plan_ms_mean,train_seconds" > "$out"
while [ $e -lt $last ]; do
  echo "$e,$((seed * 100 + e)).5,200,${{WALL:-0.010}},200,12.500,1.250" >> "$out"
  e=$((e + 1))
  echo $e > "$state"
  # The real bridge's rule at a deadline: the next episode takes as long as this one.
  wall=${{WALL:-0.010}}
  if [ -n "$deadline" ] && [ $(( $(date +%s) + ${{wall%.*}} )) -gt "$deadline" ] && [ $e -lt $last ]; then
    echo $e > {dir}/stopped-after; exit 0
  fi
  if [ "$SLOW_SEED" = "$seed" ]; then
    trap "echo $e > {dir}/stopped-after; exit 143" TERM
    sleep 5 & wait $!
  fi
  if [ "$FAIL_SEED" = "$seed" ]; then exit 3; fi
  if [ "$HANG_SEED" = "$seed" ]; then echo $$ > "{dir}/hung.pid"; exec sleep 300; fi
done
"#,
            calls = calls.display(),
            dir = dir.display()
        ),
    );
}

fn experiment(bins: &Path, out: &Path, fail_seed: Option<u32>) -> std::process::Output {
    let mut cmd = exe();
    cmd.args([
        "experiment",
        "--task",
        "cartpole",
        "--methods",
        "cem,cem+deen",
    ])
    .args([
        "--seeds",
        "2",
        "--episodes",
        "3",
        "--scale",
        "small",
        "--jobs",
        "2",
    ])
    .arg("--out")
    .arg(out)
    .arg("--bin-dir")
    .arg(bins);
    if let Some(seed) = fail_seed {
        cmd.env("FAIL_SEED", seed.to_string());
    }
    cmd.output().unwrap()
}

fn calls(bins: &Path) -> Vec<String> {
    std::fs::read_to_string(bins.join("calls.log"))
        .unwrap_or_default()
        .lines()
        .map(str::to_string)
        .collect()
}

/// The episode numbers of one run in `episodes.csv`, in file order.
fn episodes_of(out: &Path, method: &str, seed: u64) -> Vec<u32> {
    std::fs::read_to_string(out.join("episodes.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[1] == method && f[2] == seed.to_string()).then(|| f[3].parse().unwrap())
        })
        .collect()
}

/// The launcher itself killed (SIGKILL) while a bridge is one episode into a run: the next
/// launch keeps that episode, asks the bridge for the other two only, and the run ends with
/// exactly three episodes, none twice.
#[test]
fn an_experiment_killed_mid_run_resumes_where_it_stopped() {
    let bins = temp_dir("bins-killed");
    fake_binaries(&bins);
    let out = bins.join("results");
    let mut cmd = one_run_sitting(&bins, &out);
    cmd.env("HANG_SEED", "0")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null());
    let mut launcher = cmd.spawn().unwrap();
    let pid_file = wait_until_hung(&bins);
    launcher.kill().unwrap();
    launcher.wait().unwrap();
    // The bridge (and the daemon) were told to stop with the launcher: the hung stand-in's
    // `sleep` gets SIGTERM from the kernel.
    let hung = std::fs::read_to_string(&pid_file).unwrap();
    let started = std::time::Instant::now();
    while alive(&hung) {
        if started.elapsed().as_secs() > 30 {
            Command::new("kill").arg(hung.trim()).status().unwrap();
            panic!("the bridge outlived the launcher");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    assert!(!out.join("runs/cem-s0.csv").exists());

    let second = experiment_once(&bins, &out);
    assert!(
        second.status.success(),
        "{}",
        String::from_utf8_lossy(&second.stderr)
    );
    let all = calls(&bins);
    assert_eq!(all.len(), 2, "{all:?}");
    assert!(
        all[0].contains("--episodes 3") && all[1].contains("--episodes 2"),
        "{all:?}"
    );
    let run_name = |call: &str| {
        let name = call
            .split("--run ")
            .nth(1)
            .and_then(|r| r.split_whitespace().next());
        name.map(str::to_string)
    };
    assert_eq!(
        run_name(&all[0]),
        run_name(&all[1]),
        "one daemon run: {all:?}"
    );
    assert!(run_name(&all[0]).is_some(), "{all:?}");
    assert_eq!(episodes_of(&out, "cem", 0), [0, 1, 2]);
    std::fs::remove_dir_all(&bins).unwrap();
}

/// Whether process `pid` runs: its /proc entry exists and is not a zombie waiting to be reaped.
fn alive(pid: &str) -> bool {
    std::fs::read_to_string(format!("/proc/{}/stat", pid.trim())).is_ok_and(|stat| {
        stat.rsplit(')')
            .next()
            .map(str::trim_start)
            .is_some_and(|r| !r.starts_with('Z'))
    })
}

/// Ctrl-C in the launcher's terminal (SIGINT to its process group) while a bridge is one
/// episode into a run (and a second sitting on the same folder refused meanwhile): the sitting
/// stops cleanly, the bridge and then the daemon stopped, the recorded episode kept in the
/// run's partial file, and the same command continues the run.
#[test]
fn ctrl_c_stops_the_sitting_cleanly_and_the_same_command_continues() {
    use std::os::unix::process::CommandExt;
    let bins = temp_dir("bins-ctrl-c");
    fake_binaries(&bins);
    let out = bins.join("results");
    let mut cmd = one_run_sitting(&bins, &out);
    cmd.env("HANG_SEED", "0")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        // A terminal's foreground job: Ctrl-C signals the whole group.
        .process_group(0);
    let launcher = cmd.spawn().unwrap();
    let pid_file = wait_until_hung(&bins);
    // A second sitting on the same folder is refused before it touches anything.
    let second = experiment_once(&bins, &out);
    assert!(!second.status.success());
    says(&second.stderr, "another sitting is running in");
    assert_eq!(calls(&bins).len(), 1, "no second bridge started");
    let group = i32::try_from(launcher.id()).unwrap();
    // SAFETY: kill with the group of our own child and a valid signal touches no memory.
    assert_eq!(unsafe { libc::kill(-group, libc::SIGINT) }, 0);
    let ended = launcher.wait_with_output().unwrap();
    let hung = std::fs::read_to_string(&pid_file).unwrap();
    let planner = std::fs::read_to_string(bins.join("planner.pid")).unwrap();
    for pid in [&hung, &planner] {
        if alive(pid) {
            Command::new("kill").arg(pid.trim()).status().unwrap();
            panic!("a child outlived the stopped sitting");
        }
    }
    let stderr = String::from_utf8_lossy(&ended.stderr);
    assert!(ended.status.success(), "{stderr}");
    says(&ended.stderr, "run cem-s0 stopped on request");
    says(
        &ended.stderr,
        "stopped on request: every unfinished run kept",
    );
    let partial = std::fs::read_to_string(out.join("runs/cem-s0.csv.partial")).unwrap();
    assert_eq!(
        partial.lines().count(),
        2,
        "header and episode 0: {partial}"
    );
    assert!(!out.join("runs/cem-s0.csv.attempt").exists());
    assert!(!out.join("runs/cem-s0.csv").exists());

    let second = experiment_once(&bins, &out);
    succeeded(&second);
    let all = calls(&bins);
    assert!(all.len() == 2 && all[1].contains("--episodes 2"), "{all:?}");
    assert_eq!(episodes_of(&out, "cem", 0), [0, 1, 2]);
    std::fs::remove_dir_all(&bins).unwrap();
}

/// The command of a sitting of one cem run, seed 0, three episodes.
fn one_run_sitting(bins: &Path, out: &Path) -> Command {
    let mut cmd = exe();
    cmd.args(["experiment", "--task", "cartpole", "--methods", "cem"])
        .args(["--seeds", "1", "--episodes", "3", "--scale", "small"])
        .arg("--out")
        .arg(out)
        .arg("--bin-dir")
        .arg(bins);
    cmd
}

/// Runs [`one_run_sitting`] to its end.
fn experiment_once(bins: &Path, out: &Path) -> std::process::Output {
    one_run_sitting(bins, out).output().unwrap()
}

/// Waits for a stand-in bridge started with HANG_SEED to hang; returns its pid file.
fn wait_until_hung(bins: &Path) -> PathBuf {
    let pid_file = bins.join("hung.pid");
    let started = std::time::Instant::now();
    while !pid_file.exists() {
        assert!(started.elapsed().as_secs() < 60, "the bridge never hung");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    pid_file
}

#[test]
fn experiment_writes_the_schema_and_resumes_only_unfinished_runs() {
    let bins = temp_dir("bins");
    fake_binaries(&bins);
    let out = bins.join("results");

    // First attempt: every seed-1 run fails after one episode.
    let first = experiment(&bins, &out, Some(1));
    assert!(!first.status.success());
    let stderr = String::from_utf8_lossy(&first.stderr);
    assert!(stderr.contains("2 run(s) failed"), "{stderr}");
    assert_eq!(calls(&bins).len(), 4);
    // The bridges got the run spec: the method's preset and the small scale's overrides.
    let all = calls(&bins).join("\n");
    assert!(
        all.contains("--preset cem+deen") && all.contains("--population 200"),
        "{all}"
    );
    let csv = std::fs::read_to_string(out.join("episodes.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "task,method,seed,episode,return,steps,planned_steps,plan_ms_per_step,train_seconds,wall_seconds"
    );
    let rows: Vec<&str> = lines.collect();
    assert_eq!(rows.len(), 6, "{csv}");
    assert_eq!(rows[0], "cartpole,cem,0,0,0.5,200,200,12.500,1.250,0.010");
    assert!(
        rows.iter().all(|r| r.split(',').nth(2) == Some("0")),
        "{csv}"
    );
    assert!(out.join("runs/cem-s1.csv.partial").exists());
    // The unfinished run keeps the sitting that recorded its first episode.
    let sittings: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("runs/cem-s1.sittings.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(
        sittings[0]["episodes"],
        serde_json::json!([0]),
        "{sittings}"
    );
    assert!(out.join("learning_curves.png").exists());

    // Second attempt: only the two failed runs start again, each resumed for its two missing
    // episodes, and all 12 rows are there, every episode once.
    let second = experiment(&bins, &out, None);
    assert!(
        second.status.success(),
        "{}",
        String::from_utf8_lossy(&second.stderr)
    );
    let after = calls(&bins);
    assert_eq!(after.len(), 6, "{after:?}");
    assert!(
        after[4..]
            .iter()
            .all(|c| c.contains("--seed 1") && c.contains("--episodes 2")),
        "{after:?}"
    );
    assert_eq!(episodes_of(&out, "cem+deen", 1), [0, 1, 2]);
    assert_eq!(episodes_of(&out, "cem", 1), [0, 1, 2]);
    let csv = std::fs::read_to_string(out.join("episodes.csv")).unwrap();
    assert_eq!(csv.lines().count(), 13, "{csv}");
    assert!(
        csv.contains("cartpole,cem+deen,1,2,102.5,200,200,12.500,1.250,0.010"),
        "{csv}"
    );

    // Each finished run's record has one entry per sitting that recorded its episodes: which
    // episodes, on which machine, and the kernels the daemon reported for it.
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("runs/cem-deen-s1.json")).unwrap())
            .unwrap();
    let sittings = record["sittings"].as_array().unwrap();
    assert_eq!(sittings.len(), 2, "{record}");
    assert_eq!(sittings[0]["episodes"], serde_json::json!([0]), "{record}");
    assert_eq!(
        sittings[1]["episodes"],
        serde_json::json!([1, 2]),
        "{record}"
    );
    for sitting in sittings {
        assert_eq!(sitting["kernels"]["precision"], "auto", "{record}");
        assert_eq!(sitting["kernels"]["dynamics"], "amx-bf16", "{record}");
        assert_eq!(sitting["kernels"]["energy"], "avx512-f32", "{record}");
        assert!(
            sitting["machine"]["cpu_path"]
                .as_str()
                .unwrap()
                .ends_with("scalar-f32"),
            "{record}"
        );
    }
    // The finished run's sittings moved into its record; a run finished in one sitting has one.
    assert!(!out.join("runs/cem-deen-s1.sittings.json").exists());
    let one: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("runs/cem-s0.json")).unwrap())
            .unwrap();
    assert_eq!(
        one["sittings"][0]["episodes"],
        serde_json::json!([0, 1, 2]),
        "{one}"
    );

    // Third attempt: nothing left to do, nothing started.
    let third = experiment(&bins, &out, None);
    assert!(third.status.success());
    assert_eq!(calls(&bins).len(), 6);
    std::fs::remove_dir_all(&bins).unwrap();
}

/// `--exploration-episodes` reaches every method's bridge and the folder's record, and a
/// command with another value into the same folder is refused (its runs would be another
/// experiment).
#[test]
fn exploration_episodes_reach_the_bridges_and_the_record() {
    let bins = temp_dir("bins-exploration");
    fake_binaries(&bins);
    let out = bins.join("results");
    let run = |episodes: &str| {
        exe()
            .args([
                "experiment",
                "--task",
                "cartpole",
                "--methods",
                "cem,cem+deen",
            ])
            .args(["--seeds", "1", "--episodes", "3", "--scale", "small"])
            .args(["--exploration-episodes", episodes])
            .arg("--out")
            .arg(&out)
            .arg("--bin-dir")
            .arg(&bins)
            .output()
            .unwrap()
    };
    succeeded(&run("2"));
    let all = calls(&bins);
    assert_eq!(all.len(), 2, "{all:?}");
    assert!(
        all.iter().all(|c| c.contains("--exploration-episodes 2")),
        "{all:?}"
    );
    let manifest = std::fs::read_to_string(out.join("experiment.json")).unwrap();
    assert_eq!(
        manifest.matches("\"exploration_episodes\": 2").count(),
        2,
        "{manifest}"
    );
    let other = run("3");
    assert!(!other.status.success());
    says(&other.stderr, "overrides");
    // No random episode at all would leave the first plan without models.
    let none = run("0");
    assert!(!none.status.success());
    says(&none.stderr, "--exploration-episodes");
    std::fs::remove_dir_all(&bins).unwrap();
}

/// The daemon and every bridge of a sitting start from one Zenoh file whose link lease is an
/// hour: an idle-priority process starved of a core for longer than Zenoh's default 10 s is
/// not taken for dead (which made every bridge start its episode over). The daemon's
/// configuration lifts the retraining budget to a day, the bridges' wait for it: an
/// experiment trains its preset's full epochs however slow the machine.
#[test]
fn every_process_of_a_sitting_shares_a_long_link_lease_and_training_is_not_cut_short() {
    let bins = temp_dir("bins-lease");
    fake_binaries(&bins);
    let out = bins.join("results");
    succeeded(&experiment(&bins, &out, None));
    let zenoh = out.join("logs").join("zenoh.json5");
    let link: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&zenoh).unwrap()).unwrap();
    assert_eq!(
        link["transport"]["link"]["tx"]["lease"],
        serde_json::json!(3_600_000),
        "{link}"
    );
    let toml = out.join("logs").join("planner.toml");
    let daemon = planner_service::config::ServiceConfig::load(&toml).unwrap();
    assert_eq!(daemon.zenoh_config.as_deref(), Some(zenoh.as_path()));
    assert!((daemon.limits.max_retrain_seconds - 86_400.0).abs() < 1e-9);
    let serve = std::fs::read_to_string(bins.join("planner-calls.log")).unwrap();
    assert!(
        serve.starts_with("serve ") && serve.contains(&format!("--config {}", toml.display())),
        "{serve}"
    );
    let bridges = calls(&bins);
    assert_eq!(bridges.len(), 4, "{bridges:?}");
    let flags = [
        format!("--zenoh-config {}", zenoh.display()),
        "--train-timeout 86400".to_string(),
    ];
    assert!(
        bridges.iter().all(|c| flags.iter().all(|f| c.contains(f))),
        "{bridges:?}"
    );
    std::fs::remove_dir_all(&bins).unwrap();
}

/// With a budget, the bridge is given the sitting's deadline, and a run whose next episode (as
/// long as its last, 60 s) would end after it stops at the episode boundary (the bridge's own
/// decision, before it resets) rather than at the deadline with an episode cut short; the
/// launcher takes that clean early exit for a deadline stop: the sitting ends with one recorded
/// episode and the run resumable.
#[test]
fn a_budget_stops_a_run_between_episodes() {
    let bins = temp_dir("bins-boundary");
    fake_binaries(&bins);
    let out = bins.join("results");
    let started = std::time::Instant::now();
    let output = exe()
        .args(["experiment", "--task", "cartpole", "--methods", "cem"])
        .args(["--seeds", "1", "--episodes", "3", "--scale", "small"])
        .args(["--budget", "8s"])
        .arg("--out")
        .arg(&out)
        .arg("--bin-dir")
        .arg(&bins)
        .env("SLOW_SEED", "0")
        .env("WALL", "60.000")
        .output()
        .unwrap();
    succeeded(&output);
    let stderr = String::from_utf8_lossy(&output.stderr);
    let stopped = std::fs::read_to_string(bins.join("stopped-after")).unwrap();
    assert_eq!(
        stopped.trim(),
        "1",
        "stopped after the first episode: {stderr}"
    );
    assert!(
        stderr.contains("stopped after this episode"),
        "the launcher says why: {stderr}"
    );
    assert!(
        !out.join("runs/cem-s0.csv").exists(),
        "the run is unfinished"
    );
    let bridge = calls(&bins).concat();
    let deadline: u64 = bridge
        .split("--deadline ")
        .nth(1)
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|at| at.parse().ok())
        .unwrap_or_else(|| panic!("the bridge is given the deadline: {bridge}"));
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs();
    assert!(
        deadline + 30 > now && deadline < now + 10,
        "deadline {deadline}, now {now}: the budget's 8 s, in Unix seconds"
    );
    let partial = std::fs::read_to_string(out.join("runs/cem-s0.csv.partial")).unwrap();
    assert_eq!(
        partial.lines().count(),
        2,
        "header and one episode: {partial}"
    );
    assert!(
        started.elapsed() < std::time::Duration::from_secs(8),
        "stopped before the deadline, not at it"
    );
    std::fs::remove_dir_all(&bins).unwrap();
}

/// `imagination` into one folder over two sittings: the second skips the seed the first
/// recorded and adds the next; a budget the recorded seeds' mean time does not fit leaves a seed
/// for later; other settings in the same folder are refused.
#[test]
fn imagination_seeds_accumulate_in_their_folder() {
    let out = temp_dir("imagination-folder");
    let imagination = |seeds: &str, mpc_steps: &str, budget: Option<&str>| {
        let mut cmd = exe();
        cmd.args(["imagination", "--task", "cartpole", "--scale", "small"])
            .args(["--plan-scale", "small", "--episodes", "2", "--states", "2"])
            .args(["--mpc-steps", mpc_steps, "--seeds", seeds])
            .arg("--out")
            .arg(&out);
        if let Some(budget) = budget {
            cmd.args(["--budget", budget]);
        }
        cmd.output().unwrap()
    };
    let seeds_in = |out: &Path| -> Vec<String> {
        std::fs::read_to_string(out.join("imagination_seeds.csv"))
            .unwrap()
            .lines()
            .skip(1)
            .map(|l| l.split(',').next().unwrap().to_string())
            .collect()
    };
    let first = imagination("1", "5", None);
    succeeded(&first);
    assert_eq!(seeds_in(&out), ["0"]);
    let states = std::fs::read_to_string(out.join("imagination_states.csv")).unwrap();
    let figure = std::fs::read(out.join("imagination.csv")).unwrap();

    // Seed 0's wall time is far more than a second: a 1 s budget starts nothing new.
    let short = imagination("2", "5", Some("1s"));
    succeeded(&short);
    says(&short.stdout, "seeds [1] do not fit");
    assert_eq!(seeds_in(&out), ["0"]);

    let second = imagination("2", "5", None);
    succeeded(&second);
    says(&second.stderr, "seed 0: already in");
    assert_eq!(seeds_in(&out), ["0", "1"]);
    let both = std::fs::read_to_string(out.join("imagination_states.csv")).unwrap();
    assert!(
        both.starts_with(&states),
        "seed 0's rows are kept as they were"
    );
    assert_eq!(
        both.lines().count(),
        1 + 2 * 2 * 3,
        "2 seeds x 2 states x 3 regularisers"
    );
    assert_eq!(std::fs::read(out.join("imagination.csv")).unwrap(), figure);

    let other = imagination("2", "7", None);
    assert!(!other.status.success());
    says(&other.stderr, "another comparison");
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn compare_prints_intervals_per_method_and_seed_paired_and_refuses_bad_arguments() {
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/episodes.csv");
    let compare = |args: &[&str]| {
        exe()
            .arg("compare")
            .arg(&fixture)
            .args(args)
            .output()
            .unwrap()
    };

    let out = compare(&["--episode", "2"]);
    succeeded(&out);
    // cem 110 and 150 (mean 130), cem+deen 170 and 175; t(0.975, 1 dof) = 12.706.
    says(&out.stdout, "| 2 | `cem` | 2 | 130 | [−124, 384] |");
    says(&out.stdout, "| 2 | `cem+deen` − `cem` | 2 |");
    says(&out.stdout, "| [−180, 265] | 2 of 2 | overlap |");

    let out = compare(&["--episode", "3"]);
    assert!(!out.status.success());
    says(&out.stderr, "no run has episode 3 (from 0)");
    let out = compare(&["--episode", "2,3"]);
    assert!(!out.status.success(), "one episode missing fails the whole");
    // Several episodes, one table: each episode's rows in the order asked.
    let out = compare(&["--episode", "last,2", "--only", "methods"]);
    succeeded(&out);
    let table = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<&str> = table.lines().collect();
    assert!(lines.iter().all(|l| l.starts_with('|')), "{table}");
    assert_eq!(
        lines.len(),
        2 + 2 * 2,
        "header, rule, 2 episodes x 2 methods: {table}"
    );
    assert!(
        lines[2].starts_with("| last | `cem` | 2 | 130 | [−124, 384] |"),
        "{table}"
    );
    assert!(lines[4].starts_with("| 2 | `cem` |"), "{table}");
    let out = compare(&["--episode", "2", "--only", "differences"]);
    succeeded(&out);
    let table = String::from_utf8(out.stdout).unwrap();
    assert!(table.starts_with("| episode | difference |"), "{table}");
    assert_eq!(table.lines().count(), 3, "{table}");
    let out = compare(&["--episode", "2", "--only", "prose"]);
    assert!(!out.status.success());
    // Only the methods asked for; a method the experiments lack is named in the error.
    let out = compare(&["--episode", "2", "--methods", "cem", "--only", "methods"]);
    succeeded(&out);
    assert_eq!(String::from_utf8(out.stdout).unwrap().lines().count(), 3);
    let out = compare(&["--episode", "2", "--methods", "cem,pets"]);
    assert!(!out.status.success());
    says(
        &out.stderr,
        "no run of method `pets`: the experiments hold cem, cem+deen",
    );
    let out = compare(&["--episode", "2", "--level", "95"]);
    assert!(!out.status.success());
    says(&out.stderr, "not a level between 0 and 1");
}

/// Fails the test with the command's stderr unless it succeeded.
fn succeeded(output: &std::process::Output) {
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

/// Fails the test unless `stream` (a command's stdout or stderr) contains `text`.
fn says(stream: &[u8], text: &str) {
    let stream = String::from_utf8_lossy(stream);
    assert!(stream.contains(text), "no `{text}` in: {stream}");
}
