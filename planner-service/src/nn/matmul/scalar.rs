//! The portable kernel: plain loops over rows of `Y` that the compiler vectorises at SSE2 width.

use super::{Raw, RawInit};

/// # Safety
/// Every extent of `raw` must be valid (as checked by `matmul`).
pub(super) unsafe fn drive(raw: &Raw) {
    let Raw {
        m,
        n,
        k,
        x,
        rs_x,
        cs_x,
        y,
        ld_y,
        c,
        ld_c,
        init,
        act,
    } = *raw;
    assert!(
        act.is_none(),
        "the portable kernel has no activation epilogue"
    );
    for i in 0..m {
        // SAFETY: row `i` of C holds `n` floats inside the checked extent, and C does not
        // overlap X or Y (it is borrowed mutably while they are borrowed shared).
        let c_row = unsafe { std::slice::from_raw_parts_mut(c.add(i * ld_c), n) };
        match init {
            RawInit::Zero => c_row.fill(0.0),
            RawInit::Accumulate => {}
            // SAFETY: the bias holds at least `m` (row) or `n` (column) floats.
            RawInit::RowBias(b) => c_row.fill(unsafe { *b.add(i) }),
            RawInit::ColBias(b) => {
                c_row.copy_from_slice(unsafe { std::slice::from_raw_parts(b, n) })
            }
        }
        for d in 0..k {
            // SAFETY: `(i, d)` of X and row `d` of Y are inside their checked extents.
            let (xv, y_row) = unsafe {
                (
                    *x.add(i * rs_x + d * cs_x),
                    std::slice::from_raw_parts(y.add(d * ld_y), n),
                )
            };
            for (cv, yv) in c_row.iter_mut().zip(y_row) {
                *cv += xv * yv;
            }
        }
    }
}
