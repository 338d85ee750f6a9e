//! Evaluating an expression for a population allocates nothing once its scratch exists: the
//! planner calls it for every imagined step of every candidate.
//!
//! A test binary of its own, because it installs a counting global allocator; it counts only
//! on the thread that asks (the test harness's threads allocate as they please).

use proto::task::expression::{Dims, Expression, Gradients, Inputs};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;

thread_local! {
    /// Allocations on this thread while counting, or `None` when not counting.
    static ALLOCATIONS: Cell<Option<usize>> = const { Cell::new(None) };
}

fn count() {
    ALLOCATIONS.with(|c| c.set(c.get().map(|n| n + 1)));
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn evaluation_and_gradients_allocate_nothing() {
    let dims = Dims {
        obs_dim: 18,
        act_dim: 6,
    };
    let e = Expression::parse(
        "s_next[0] - 0.1*dot(a, a) + if(norm(s_next[1:4]) > 1, -1, tanh(s[2]))",
        dims,
    )
    .unwrap();
    let rows = 500 * 30 + 7;
    let s: Vec<f32> = (0..rows * 18)
        .map(|i| (i % 13) as f32 * 0.1 - 0.6)
        .collect();
    let a: Vec<f32> = (0..rows * 6).map(|i| (i % 7) as f32 * 0.2 - 0.6).collect();
    let n: Vec<f32> = (0..rows * 18)
        .map(|i| (i % 11) as f32 * 0.1 - 0.5)
        .collect();
    let mut out = vec![0.0; rows];
    let (mut ds, mut da, mut dn) = (
        vec![0.0; rows * 18],
        vec![0.0; rows * 6],
        vec![0.0; rows * 18],
    );
    let mut scratch = e.scratch();
    let inputs = Inputs {
        s: &s,
        a: &a,
        s_next: &n,
    };

    ALLOCATIONS.with(|c| c.set(Some(0)));
    for _ in 0..3 {
        e.eval_batch(inputs, &mut out, &mut scratch);
        let grads = Gradients {
            s: &mut ds,
            a: &mut da,
            s_next: &mut dn,
        };
        e.eval_grad(inputs, &mut out, grads, &mut scratch);
    }
    let allocations = ALLOCATIONS.with(|c| c.replace(None));
    assert_eq!(allocations, Some(0));
    // The work was done: the action's gradient is −0.2a.
    assert!((da[1] + 0.2 * a[1]).abs() < 1e-6 && out.iter().all(|x| x.is_finite()));
}
