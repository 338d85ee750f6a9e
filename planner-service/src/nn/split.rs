//! Whether a thread may split its work (a large product, an Adam update) across rayon's
//! threads.
//!
//! A retraining trains the dynamics model and the regulariser at the same time, one on each
//! core ([`crate::trainer::retrain`]). While both train, the other core is taken: splitting a
//! product would only queue its second half behind the partner's work (or, from a thread
//! outside rayon's pool, hand both halves to the pool and wait), and the two helpers would meet
//! after every product. So each keeps its products whole on its own thread until its partner
//! is done; from then on the one still training splits its large products again and gets both
//! cores.

use std::cell::RefCell;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

thread_local! {
    /// Raised while this thread's training partner still trains.
    static PARTNER_BUSY: RefCell<Option<Arc<AtomicBool>>> = const { RefCell::new(None) };
}

/// Runs `f` on this thread with its work kept whole while `partner_busy` is raised (the
/// partner lowers it when it is done). Restores the previous state afterwards, also when `f`
/// panics.
pub fn beside_partner<R>(partner_busy: &Arc<AtomicBool>, f: impl FnOnce() -> R) -> R {
    struct Restore(Option<Arc<AtomicBool>>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let previous = self.0.take();
            PARTNER_BUSY.with(|p| *p.borrow_mut() = previous);
        }
    }
    let previous = PARTNER_BUSY.with(|p| p.borrow_mut().replace(partner_busy.clone()));
    let _restore = Restore(previous);
    f()
}

/// Whether work on this thread may be split across rayon's threads now: not while a training
/// partner holds the other core.
pub fn may_split() -> bool {
    PARTNER_BUSY.with(|p| {
        p.borrow()
            .as_ref()
            .is_none_or(|busy| !busy.load(Ordering::Acquire))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn work_stays_whole_only_while_the_partner_is_busy() {
        assert!(may_split());
        let busy = Arc::new(AtomicBool::new(true));
        beside_partner(&busy, || {
            assert!(!may_split());
            busy.store(false, Ordering::Release);
            assert!(may_split(), "the partner is done: both cores are free");
        });
        busy.store(true, Ordering::Release);
        assert!(may_split(), "outside the scope the flag is not consulted");
        // Other threads are not affected.
        beside_partner(&busy, || {
            assert!(std::thread::spawn(may_split).join().unwrap());
        });
        // A panic inside restores the state.
        let caught = std::panic::catch_unwind(|| beside_partner(&busy, || panic!("boom")));
        assert!(caught.is_err());
        assert!(may_split());
    }
}
