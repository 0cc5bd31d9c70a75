//! Typed errors of the tape: shape problems name the op and the shapes involved.

use thiserror::Error;

/// Which pass an anomaly was found in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pass {
    /// The op's forward output held a NaN or Inf.
    Forward,
    /// A gradient the op's backward produced held a NaN or Inf.
    Backward,
}

impl std::fmt::Display for Pass {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Pass::Forward => "forward",
            Pass::Backward => "backward",
        })
    }
}

/// Everything that can go wrong on the tape.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum AutodiffError {
    /// Input shapes that the op cannot combine.
    #[error("{op}: incompatible shapes {shapes:?}: {detail}")]
    Shape {
        /// Name of the op.
        op: &'static str,
        /// Shapes of the inputs involved.
        shapes: Vec<Vec<usize>>,
        /// What was expected.
        detail: String,
    },
    /// An axis or index argument out of range.
    #[error("{op}: {detail} (input shapes {shapes:?})")]
    Index {
        /// Name of the op.
        op: &'static str,
        /// Shapes of the inputs involved.
        shapes: Vec<Vec<usize>>,
        /// What was out of range.
        detail: String,
    },
    /// An argument that is not a shape or index problem (e.g. a negative epsilon).
    #[error("{op}: invalid argument: {detail}")]
    InvalidArgument {
        /// Name of the op or function.
        op: &'static str,
        /// What was wrong.
        detail: String,
    },
    /// Anomaly detection found a NaN or Inf (see [`crate::Tape::set_detect_anomaly`]).
    #[error("anomaly: {op} (node {node}) produced a non-finite value in its {pass} pass; input shapes {input_shapes:?}")]
    Anomaly {
        /// Name of the op.
        op: &'static str,
        /// Index of the op's first output variable on the tape.
        node: usize,
        /// Forward or backward.
        pass: Pass,
        /// Shapes of the op's inputs.
        input_shapes: Vec<Vec<usize>>,
    },
    /// A variable from another tape, or used after an error poisoned it.
    #[error("{0}")]
    Tape(String),
    /// A custom op failed in its own way.
    #[error("{op}: {detail}")]
    Op {
        /// Name of the op.
        op: &'static str,
        /// The op's message.
        detail: String,
    },
}

impl AutodiffError {
    /// Shape error helper.
    pub fn shape(op: &'static str, shapes: &[&[usize]], detail: impl Into<String>) -> Self {
        AutodiffError::Shape {
            op,
            shapes: shapes.iter().map(|s| s.to_vec()).collect(),
            detail: detail.into(),
        }
    }
    /// Index error helper.
    pub fn index(op: &'static str, shapes: &[&[usize]], detail: impl Into<String>) -> Self {
        AutodiffError::Index {
            op,
            shapes: shapes.iter().map(|s| s.to_vec()).collect(),
            detail: detail.into(),
        }
    }
    /// Invalid-argument helper.
    pub fn invalid(op: &'static str, detail: impl Into<String>) -> Self {
        AutodiffError::InvalidArgument {
            op,
            detail: detail.into(),
        }
    }
}

/// Result alias of the crate.
pub type Result<T, E = AutodiffError> = std::result::Result<T, E>;
