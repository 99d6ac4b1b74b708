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

pub mod batch;
pub mod delan;
pub mod dynamics;
pub mod encoder;
pub mod error;
pub mod grad;
pub mod ext;
mod lanes;
pub mod lane_rollout;
mod lane_tail;
mod math;
mod math32;
pub mod mlp;
pub mod loader;
pub mod model;
pub mod pool;
mod real;
pub mod rollout;
pub mod simd;
mod single_f32;
pub mod synth;
pub mod tcn;
pub mod timing;

pub use delan::{ExoTorque, Workspace, COND_MAX};
pub use encoder::EncoderState;
pub use lane_rollout::LaneWorkspace;
pub use error::{Error, Result};
pub use model::{EncoderKind, JointType, Meta, Model, Simd};
pub use pool::Pool;
pub use rollout::{Inputs, ZSeq};

#[cfg(feature = "python")]
mod python;
#[cfg(feature = "python")]
mod python_conv;
#[cfg(feature = "python")]
mod python_engine;
#[cfg(feature = "python")]
mod python_grad;
#[cfg(feature = "python")]
mod python_tcn;
