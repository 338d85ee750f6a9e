//! Pinning: the run-name patterns a planner serves, or refuses (`[fleet]` in its config).
//!
//! Patterns are globs over whole run names: `*` matches any run of characters, `?` one
//! character, everything else itself. A planner with `serve` patterns is a candidate only for
//! the runs they match; `refuse` patterns take it out of the candidates for the runs they
//! match, whatever `serve` says. Every planner publishes its pins (see `crate::fleet::Fleet`), so all
//! planners apply the same rules when they place a run.

use serde::{Deserialize, Serialize};

/// Longest pattern accepted, like a name.
const MAX_PATTERN: usize = 64;
/// Most patterns per list: a fleet profile travels in one small query reply.
const MAX_PATTERNS: usize = 64;

/// A planner's pins.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Pins {
    /// Run-name patterns this planner serves (empty: every run it is not told to refuse).
    pub serve: Vec<String>,
    /// Run-name patterns this planner never serves.
    pub refuse: Vec<String>,
}

/// A pattern that cannot match a run name.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PinsError {
    #[error(
        "invalid run-name pattern `{0}`: use 1-64 characters from letters, digits, '-', '_', '.', '*' and '?'"
    )]
    Pattern(String),
    #[error("{list} has {found} patterns; at most {MAX_PATTERNS}")]
    TooMany { list: &'static str, found: usize },
}

impl Pins {
    /// Checks every pattern (the same characters as names, plus the two wildcards).
    pub fn validate(&self) -> Result<(), PinsError> {
        for (list, patterns) in [("serve", &self.serve), ("refuse", &self.refuse)] {
            if patterns.len() > MAX_PATTERNS {
                return Err(PinsError::TooMany {
                    list,
                    found: patterns.len(),
                });
            }
            for pattern in patterns {
                let ok = !pattern.is_empty()
                    && pattern.len() <= MAX_PATTERN
                    && pattern.chars().all(|c| {
                        c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.' | '*' | '?')
                    });
                if !ok {
                    return Err(PinsError::Pattern(pattern.clone()));
                }
            }
        }
        Ok(())
    }

    /// Whether a planner with these pins may own `run`.
    pub fn allows(&self, run: &str) -> bool {
        let matches = |patterns: &[String]| patterns.iter().any(|p| glob(p, run));
        (self.serve.is_empty() || matches(&self.serve)) && !matches(&self.refuse)
    }
}

/// Whether `pattern` matches all of `text` (`*`: any characters, `?`: one character).
fn glob(pattern: &str, text: &str) -> bool {
    let (p, t): (Vec<char>, Vec<char>) = (pattern.chars().collect(), text.chars().collect());
    // Iterative matching with one backtrack point for the last `*`: linear for these sizes.
    let (mut pi, mut ti) = (0, 0);
    let mut star: Option<(usize, usize)> = None;
    while ti < t.len() {
        if pi < p.len() && (p[pi] == '?' || p[pi] == t[ti]) {
            pi += 1;
            ti += 1;
        } else if pi < p.len() && p[pi] == '*' {
            star = Some((pi, ti));
            pi += 1;
        } else if let Some((sp, st)) = star {
            pi = sp + 1;
            ti = st + 1;
            star = Some((sp, st + 1));
        } else {
            return false;
        }
    }
    p[pi..].iter().all(|&c| c == '*')
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn globs_match_whole_names() {
        for (pattern, text, expected) in [
            ("cartpole-*", "cartpole-deen", true),
            ("cartpole-*", "cartpole-", true),
            ("cartpole-*", "xcartpole-a", false),
            ("*-deen", "ant-deen", true),
            ("*-deen", "ant-deen2", false),
            ("a?c", "abc", true),
            ("a?c", "ac", false),
            ("*", "anything", true),
            ("a*b*c", "aXXbYYc", true),
            ("a*b*c", "aXXbYY", false),
            ("exact", "exact", true),
            ("exact", "exactly", false),
        ] {
            assert_eq!(glob(pattern, text), expected, "{pattern} ~ {text}");
        }
    }

    #[test]
    fn serve_and_refuse() {
        let any = Pins::default();
        assert!(any.allows("x"));
        let pins = Pins {
            serve: vec!["ant-*".into(), "cheetah-*".into()],
            refuse: vec!["*-test".into()],
        };
        assert!(pins.allows("ant-1"));
        assert!(pins.allows("cheetah-deen"));
        assert!(!pins.allows("cartpole-1"));
        assert!(!pins.allows("ant-test"), "refuse wins over serve");
        let refuse_only = Pins {
            serve: vec![],
            refuse: vec!["gpu-*".into()],
        };
        assert!(refuse_only.allows("cartpole"));
        assert!(!refuse_only.allows("gpu-ant"));
    }

    #[test]
    fn hostile_patterns_are_refused() {
        for bad in ["", "a/b", "a b", "$*", "x#", &"x".repeat(65)] {
            let pins = Pins {
                serve: vec![bad.to_string()],
                refuse: vec![],
            };
            assert!(pins.validate().is_err(), "{bad:?}");
        }
        let many = Pins {
            serve: vec![],
            refuse: vec!["a".into(); 65],
        };
        assert!(matches!(
            many.validate(),
            Err(PinsError::TooMany {
                list: "refuse",
                found: 65
            })
        ));
        Pins {
            serve: vec!["ant-*".into(), "a?c".into()],
            refuse: vec!["*".into()],
        }
        .validate()
        .unwrap();
        // A pathological pattern is still answered (one backtrack point, no recursion).
        assert!(glob(&"*a".repeat(30), &"a".repeat(63)));
        assert!(!glob(&format!("{}b", "*a".repeat(30)), &"a".repeat(63)));
    }
}
