//! exolan: the Rust engine of a physics-consistent learned leg dynamics model.
//!
//! The core is pure Rust (no Python needed): load exported weights, evaluate the Lagrangian
//! dynamics with hand-derived derivatives, roll out with semi-implicit Euler, stream the
//! context encoder. The Python binding lives in [`python`] behind the `python` feature.

// Index loops mirror the physics' index notation (H_ij q̈_j), and `!(x > 0.0)` is deliberate:
// it is true for NaN, which every such guard must reject.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

/// Version of the crate, compared by `exolan doctor` against the Python package's version.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Sum of a slice: the trivial function the build tests call through the binding.
pub fn sum(xs: &[f64]) -> f64 {
    xs.iter().sum()
}

/// Scale a slice in place: used to prove that the binding passes numpy memory without copying.
pub fn scale_in_place(xs: &mut [f64], k: f64) {
    for x in xs.iter_mut() {
        *x *= k;
    }
}

pub mod delan;
pub mod encoder;
pub mod error;
pub mod ext;
mod math;
pub mod mlp;
pub mod model;
pub mod rollout;
pub mod synth;

pub use delan::{ExoTorque, Workspace, COND_MAX};
pub use encoder::EncoderState;
pub use error::{Error, Result};
pub use model::{EncoderKind, JointType, Meta, Model, Simd};
pub use rollout::{Inputs, ZSeq};

#[cfg(feature = "python")]
mod python;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sum_and_scale() {
        let mut v = vec![1.0, 2.0, 3.5];
        assert_eq!(sum(&v), 6.5);
        scale_in_place(&mut v, 2.0);
        assert_eq!(v, vec![2.0, 4.0, 7.0]);
    }
}
