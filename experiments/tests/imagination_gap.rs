//! The paper's claim behind Figure 5, checked on a fixed seed: on a dynamics model learned from
//! real experience, the plan CEM finds with the DEEN penalty promises less than it delivers by a
//! smaller margin than the plan found without a regulariser. Same model, same data, same start
//! state, same optimiser: the regulariser is the only difference.

use ebmpc_experiments::figures::imagination::{ImaginationConfig, run};
use ebmpc_experiments::scale::Scale;
use planner_service::energy::RegularizerKind;
use proto::TaskId;

#[test]
fn deen_narrows_the_gap_between_imagined_and_real_return() {
    let config = ImaginationConfig {
        // Half-cheetah: a 6-D action space gives an unregularised optimiser room to exploit the
        // model (on cartpole's single action the regulariser changes nothing, as in the paper).
        task: TaskId::HalfCheetah,
        scale: Scale::Small,
        plan_scale: Scale::Paper,
        method: "cem+deen".into(),
        train_episodes: 1,
        mpc_steps: 10,
        seed: 0,
    };
    let result = run(&config, |_, _| {}).expect("the experiment runs");
    let gap = |kind: RegularizerKind| {
        let (_, imagined, real) = result
            .totals()
            .into_iter()
            .find(|(k, _, _)| *k == kind)
            .expect("a plan per regulariser");
        eprintln!("{}: imagined {imagined:.3}, real {real:.3}", kind.name());
        imagined - real
    };
    let (none, deen) = (gap(RegularizerKind::None), gap(RegularizerKind::Deen));
    eprintln!("gap without regulariser {none:.3}, with DEEN {deen:.3}");
    assert!(
        deen.abs() < none.abs(),
        "DEEN's gap {deen:.3} is not smaller than the unregularised gap {none:.3}"
    );
}
