//! The seed's profile-correction MLP: one pitch of reconstructed profile in ([`SAMPLES`] values,
//! normalised as `pipeline::profile::pitch` makes them), the corrected pitch out. The model's
//! input is named `profile` and its output `corrected`, both `[batch, SAMPLES]` float32
//! (training/profile_mlp.py exports it so).

use super::{LearnedError, Model};
use ort::value::Tensor;
use rayon::prelude::*;

/// Samples of one pitch, as in the seed.
pub const SAMPLES: usize = 256;

/// Rows per run: a batch of this many pitches is 256 kB in and out, and several batches keep
/// every worker busy on a whole part (a few thousand pitches).
const BATCH_ROWS: usize = 256;

/// Corrects `profiles` (rows of [`SAMPLES`] values, row-major), batches in parallel, each on a
/// pooled session.
pub fn correct(model: &Model, profiles: &[f32]) -> Result<Vec<f32>, LearnedError> {
    assert_eq!(profiles.len() % SAMPLES, 0, "whole pitches only");
    let batches: Vec<Vec<f32>> = profiles
        .par_chunks(BATCH_ROWS * SAMPLES)
        .map(|batch| {
            model.pool.with(|session| {
                let rows = batch.len() / SAMPLES;
                let input = Tensor::from_array(([rows, SAMPLES], batch.to_vec()))?;
                let outputs = session.run(ort::inputs!["profile" => input])?;
                let (shape, values) = outputs["corrected"].try_extract_tensor::<f32>()?;
                if shape.iter().product::<i64>() as usize != batch.len() {
                    return Err(ort::Error::new(format!("output shape {shape:?} for {rows} pitches")));
                }
                Ok(values.to_vec())
            })
        })
        .collect::<Result<_, _>>()?;
    Ok(batches.concat())
}
