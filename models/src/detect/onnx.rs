//! A fixed-shape ONNX model run by tract (pure Rust, single-threaded: the same numbers for
//! any rayon pool).

use tract_onnx::prelude::*;

use super::DetectError;

/// One optimised, runnable model with one float32 input of a fixed shape.
pub(crate) struct Plan {
    name: &'static str,
    shape: [usize; 4],
    plan: Arc<TypedRunnableModel>,
}

impl Plan {
    /// Parses, optimises and plans `onnx` (the model's own input shape must be `shape`).
    pub fn new(name: &'static str, onnx: &[u8], shape: [usize; 4]) -> Result<Self, DetectError> {
        let err = |e: TractError| DetectError::Model(format!("{name}: {e}"));
        let plan = tract_onnx::onnx()
            .model_for_read(&mut std::io::Cursor::new(onnx))
            .map_err(err)?
            .into_optimized()
            .map_err(err)?
            .into_runnable()
            .map_err(err)?;
        Ok(Plan { name, shape, plan })
    }

    /// Runs the model on `input` (`shape`, row-major) and returns its float32 outputs, which
    /// must have `sizes` elements.
    pub fn run(&self, input: Vec<f32>, sizes: &[usize]) -> Result<Vec<Vec<f32>>, DetectError> {
        let err = |e: TractError| DetectError::Model(format!("{}: {e}", self.name));
        let x = tract_ndarray::Array::from_shape_vec(self.shape, input)
            .map_err(|e| DetectError::Model(format!("{}: input: {e}", self.name)))?;
        let out = self.plan.run(tvec!(Tensor::from(x).into())).map_err(err)?;
        if out.len() != sizes.len() {
            return Err(DetectError::Model(format!(
                "{}: {} outputs, expected {}",
                self.name,
                out.len(),
                sizes.len()
            )));
        }
        out.iter()
            .zip(sizes)
            .enumerate()
            .map(|(i, (t, &n))| {
                let v = t.to_plain_array_view::<f32>().map_err(err)?;
                if v.len() != n {
                    return Err(DetectError::Model(format!(
                        "{}: output {i} has {} values, expected {n}",
                        self.name,
                        v.len()
                    )));
                }
                Ok(v.iter().copied().collect())
            })
            .collect()
    }
}
