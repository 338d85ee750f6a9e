//! The daemon SIGKILLed at random moments while an agent steps loses no acknowledged
//! transition and accounts for every episode (see `ebmpc_e2e::kill_loop`). 10 kills here;
//! `EBMPC_KILLS=100 cargo test -p ebmpc-e2e --test e2e kill_loop:: -- --nocapture` for more.

use ebmpc_e2e::TempDir;
use ebmpc_e2e::kill_loop::kill_loop;

#[test]
fn sigkill_at_random_moments_loses_no_acknowledged_transition() {
    let kills = std::env::var("EBMPC_KILLS")
        .ok()
        .map(|k| k.parse().expect("EBMPC_KILLS is a number"))
        .unwrap_or(10);
    let seed = std::env::var("EBMPC_KILL_SEED")
        .ok()
        .map(|k| k.parse().expect("EBMPC_KILL_SEED is a number"))
        .unwrap_or(1);
    let dir = TempDir::new("kill-loop");
    let report = kill_loop(dir.path(), kills, seed).expect("the kill loop runs");
    println!("{report:#?}");
    assert_eq!(report.lost, 0, "{report:#?}");
    assert_eq!(report.episodes_unaccounted, 0, "{report:#?}");
    assert!(report.acknowledged > 0, "{report:#?}");
    assert_eq!(
        report.episodes_finished + report.episodes_interrupted,
        report.episodes_started
    );
}
