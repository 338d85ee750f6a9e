//! The paper's illustrative figures, computed in-process.
//!
//! - [`toy`]: Figure 3, DEEN and DAE score estimates on a 1-D Gaussian mixture.
//! - [`imagination`]: Figure 5, imagined against real rewards of plans optimised with each
//!   regulariser from a state reached by MPC; [`imagination_folder`] keeps its seeds, so that
//!   they accumulate over sittings, and [`imagination_tables`] prints its tables.

pub mod imagination;
pub mod imagination_folder;
pub mod imagination_tables;
pub mod toy;
