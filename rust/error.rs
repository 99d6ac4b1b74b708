//! One error type for the whole engine: loading, validation of inputs, numerics.
//! Plain enum with `Display` (no `thiserror`): the binding turns it into a Python exception
//! with exactly this message.

use std::fmt;

#[derive(Debug, Clone, PartialEq)]
pub enum Error {
    /// The file could not be read.
    Io(String),
    /// Not a parseable safetensors file (truncated, corrupt header, bad offsets).
    Format(String),
    /// `format` / `format_version` metadata missing or not the one this engine reads.
    Version(String),
    /// A metadata entry is missing or malformed.
    Metadata { key: String, msg: String },
    /// A required tensor is absent.
    MissingTensor(String),
    /// A tensor is not float64.
    Dtype { name: String, dtype: String },
    /// A tensor has the wrong shape.
    Shape { name: String, expected: Vec<usize>, got: Vec<usize> },
    /// A tensor this engine does not know (a typo in an exporter would otherwise go unnoticed).
    UnexpectedTensor(String),
    /// A weight is NaN or infinite.
    NonFiniteWeight(String),
    /// A valid file for something this engine does not run (e.g. a black-box method).
    Unsupported(String),
    /// A caller passed inconsistent shapes.
    InputShape(String),
    /// A caller passed NaN or infinity.
    NonFiniteInput(String),
    /// The inertia matrix cannot be inverted reliably (det ≤ 0, condition number too large).
    IllConditioned { det: f64, cond: f64 },
    /// A rollout left the finite numbers.
    Diverged { step: usize },
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Io(m) => write!(f, "cannot read weight file: {m}"),
            Error::Format(m) => write!(f, "not a valid safetensors weight file: {m}"),
            Error::Version(m) => write!(f, "unsupported weight file version: {m}"),
            Error::Metadata { key, msg } => write!(f, "bad metadata '{key}': {msg}"),
            Error::MissingTensor(n) => write!(f, "missing tensor '{n}'"),
            Error::Dtype { name, dtype } => write!(f, "tensor '{name}' has dtype {dtype}, expected F64"),
            Error::Shape { name, expected, got } => {
                write!(f, "tensor '{name}' has shape {got:?}, expected {expected:?}")
            }
            Error::UnexpectedTensor(n) => write!(f, "unexpected tensor '{n}' in weight file"),
            Error::NonFiniteWeight(n) => write!(f, "tensor '{n}' holds NaN or infinite values"),
            Error::Unsupported(m) => write!(f, "unsupported model: {m}"),
            Error::InputShape(m) => write!(f, "bad input shape: {m}"),
            Error::NonFiniteInput(m) => write!(f, "non-finite input: {m}"),
            Error::IllConditioned { det, cond } => write!(
                f,
                "inertia matrix H is singular or ill-conditioned (det = {det:e}, condition number = {cond:e})"
            ),
            Error::Diverged { step } => write!(f, "rollout diverged (non-finite state) at step {step}"),
        }
    }
}

impl std::error::Error for Error {}

pub type Result<T> = std::result::Result<T, Error>;
