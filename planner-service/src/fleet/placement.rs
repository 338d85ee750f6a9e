//! Where a run lives when no planner holds it: rendezvous (highest-random-weight) hashing.
//!
//! Every planner computes, for a run, a weight per candidate planner from a hash of the pair,
//! and the run goes to the heaviest. All planners that see the same set of live planners agree
//! without talking, and when a planner leaves, only its own runs move (each to the next
//! heaviest); when one joins, it only gains runs (and only free ones: a run whose owner is
//! alive stays with it, see `super::view`).

/// The weight of `planner` for `run`: FNV-1a over both names (with a separator no name can
/// contain), finished with SplitMix64's mixer so that similar names get unrelated weights. It
/// is fixed here, not taken from the standard library, so planners of different builds agree.
pub fn weight(planner: &str, run: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in run.bytes().chain([0xff]).chain(planner.bytes()) {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x100_0000_01b3);
    }
    h = (h ^ (h >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h = (h ^ (h >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^ (h >> 31)
}

/// The candidate `run` goes to: the heaviest, ties broken by the smaller id. `None` if there
/// is no candidate.
pub fn place<'a>(run: &str, candidates: impl IntoIterator<Item = &'a str>) -> Option<&'a str> {
    candidates
        .into_iter()
        .max_by(|a, b| weight(a, run).cmp(&weight(b, run)).then_with(|| b.cmp(a)))
}

#[cfg(test)]
mod tests {
    use super::*;

    const PLANNERS: [&str; 3] = ["pa", "pb", "pc"];

    fn runs() -> impl Iterator<Item = String> {
        (0..3000).map(|i| format!("run-{i}"))
    }

    #[test]
    fn the_same_view_gives_the_same_owner_in_any_order() {
        for run in runs().take(200) {
            let forward = place(&run, PLANNERS);
            let backward = place(&run, PLANNERS.iter().rev().copied());
            assert_eq!(forward, backward, "{run}");
            assert!(forward.is_some());
        }
        assert_eq!(place("r", std::iter::empty()), None);
        assert_eq!(place("r", ["solo"]), Some("solo"));
    }

    #[test]
    fn runs_spread_evenly() {
        let mut counts = [0usize; 3];
        for run in runs() {
            let owner = place(&run, PLANNERS).unwrap();
            counts[PLANNERS.iter().position(|p| *p == owner).unwrap()] += 1;
        }
        // 3000 runs: 1000 each expected; a fair hash stays within ±10 % (binomial σ ≈ 26).
        for (planner, count) in PLANNERS.iter().zip(counts) {
            assert!((900..=1100).contains(&count), "{planner}: {count} of 3000");
        }
    }

    #[test]
    fn a_leaving_planner_moves_only_its_own_runs() {
        let mut moved = 0;
        for run in runs() {
            let before = place(&run, PLANNERS).unwrap();
            let after = place(&run, ["pa", "pc"]).unwrap();
            if before != "pb" {
                assert_eq!(before, after, "{run} moved though its owner stayed");
            } else {
                moved += 1;
            }
            // A joining planner only takes runs to itself.
            let joined = place(&run, ["pa", "pb", "pc", "pd"]).unwrap();
            assert!(
                joined == before || joined == "pd",
                "{run}: {before} -> {joined}"
            );
        }
        assert!(moved > 0);
    }

    #[test]
    fn weights_are_fixed_across_builds() {
        // Recorded once (and computed independently): a change here would move every run of a
        // fleet whose planners run different builds.
        assert_eq!(weight("pa", "run-0"), 0x6fd3_b276_837c_a73c);
        assert_eq!(weight("pb", "run-0"), 0x3a16_753a_a2fc_042d);
        assert_ne!(
            weight("pa", "b"),
            weight("p", "ab"),
            "the separator keeps pairs apart"
        );
    }
}
