//! Rate-limited logging of refusals. A client can send refusable messages as fast as the
//! network carries them; logging each would let it fill the disk and drown every other line,
//! so at most [`PER_WINDOW`] refusals are logged per [`WINDOW`], and the number left out is
//! logged when the next window opens.

use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Refusals logged per window.
pub const PER_WINDOW: u32 = 20;
/// The window.
pub const WINDOW: Duration = Duration::from_secs(10);

/// Counts refusals per window and says which may be logged.
#[derive(Debug)]
pub struct LogLimit {
    state: Mutex<State>,
}

#[derive(Debug)]
struct State {
    window_start: Instant,
    logged: u32,
    suppressed: u64,
}

impl Default for LogLimit {
    fn default() -> Self {
        Self {
            state: Mutex::new(State {
                window_start: Instant::now(),
                logged: 0,
                suppressed: 0,
            }),
        }
    }
}

/// Whether to log a refusal, and how many were left out before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Log it; `suppressed` refusals of the previous window were not logged.
    Log { suppressed: u64 },
    /// Leave it out (it is counted).
    Skip,
}

impl LogLimit {
    /// Whether a refusal happening `now` may be logged.
    pub fn check(&self, now: Instant) -> Verdict {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        let mut suppressed = 0;
        if now.duration_since(s.window_start) >= WINDOW {
            suppressed = std::mem::take(&mut s.suppressed);
            s.window_start = now;
            s.logged = 0;
        }
        if s.logged < PER_WINDOW {
            s.logged += 1;
            Verdict::Log { suppressed }
        } else {
            s.suppressed += 1;
            Verdict::Skip
        }
    }

    /// Logs `line` (a refusal) at warn level if the limit allows.
    pub fn warn(&self, line: impl FnOnce()) {
        match self.check(Instant::now()) {
            Verdict::Skip => {}
            Verdict::Log { suppressed } => {
                if suppressed > 0 {
                    tracing::warn!(suppressed, "refusals not logged in the last window");
                }
                line();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flood_is_logged_up_to_the_limit_and_counted() {
        let limit = LogLimit::default();
        let t0 = Instant::now();
        for _ in 0..PER_WINDOW {
            assert_eq!(limit.check(t0), Verdict::Log { suppressed: 0 });
        }
        for _ in 0..1000 {
            assert_eq!(limit.check(t0 + WINDOW / 2), Verdict::Skip);
        }
        assert_eq!(limit.check(t0 + WINDOW), Verdict::Log { suppressed: 1000 });
        assert_eq!(limit.check(t0 + WINDOW), Verdict::Log { suppressed: 0 });
    }
}
