//! A 64-byte aligned, zero-initialised `f32` buffer.
//!
//! Network buffers are read by the matrix kernels in whole cache lines; aligning them (and
//! rounding their length to whole lines) keeps every vector load inside one line.

/// Floats per 64-byte cache line (and per AVX-512 register).
pub const LANES: usize = 16;

#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
struct Line([f32; LANES]);

/// A zero-initialised, 64-byte aligned `f32` buffer whose length is a multiple of [`LANES`].
#[derive(Clone, Default)]
pub struct AlignedBuf {
    lines: Vec<Line>,
}

impl AlignedBuf {
    /// A buffer of at least `len` zeros (rounded up to a multiple of [`LANES`]).
    pub fn zeros(len: usize) -> Self {
        Self {
            lines: vec![Line::default(); len.div_ceil(LANES)],
        }
    }

    pub fn len(&self) -> usize {
        self.lines.len() * LANES
    }

    pub fn is_empty(&self) -> bool {
        self.lines.is_empty()
    }

    pub fn as_slice(&self) -> &[f32] {
        // SAFETY: `Line` is `repr(C)` around `[f32; LANES]`, so the lines are `len()`
        // contiguous, initialised, properly aligned floats.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr().cast::<f32>(), self.len()) }
    }

    pub fn as_mut_slice(&mut self) -> &mut [f32] {
        // SAFETY: as in `as_slice`, and `&mut self` guarantees exclusive access.
        unsafe { std::slice::from_raw_parts_mut(self.lines.as_mut_ptr().cast::<f32>(), self.len()) }
    }
}

impl std::ops::Deref for AlignedBuf {
    type Target = [f32];

    fn deref(&self) -> &[f32] {
        self.as_slice()
    }
}

impl std::ops::DerefMut for AlignedBuf {
    fn deref_mut(&mut self) -> &mut [f32] {
        self.as_mut_slice()
    }
}

impl std::fmt::Debug for AlignedBuf {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "AlignedBuf({} floats)", self.len())
    }
}

/// `n` rounded up to a multiple of [`LANES`].
pub fn round_up(n: usize) -> usize {
    n.div_ceil(LANES) * LANES
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buffers_are_aligned_zeroed_and_rounded() {
        let buf = AlignedBuf::zeros(17);
        assert_eq!(buf.len(), 32);
        assert_eq!(buf.as_slice().as_ptr() as usize % 64, 0);
        assert!(buf.as_slice().iter().all(|v| *v == 0.0));
        assert_eq!(
            (round_up(0), round_up(1), round_up(16), round_up(17)),
            (0, 16, 16, 32)
        );
    }
}
