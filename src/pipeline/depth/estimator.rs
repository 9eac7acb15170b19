//! The depth estimators as peers behind one trait: each turns a view's focal stack into a depth
//! map with its per-pixel confidence (`peak_ratio`) and names what made it ([`DepthEstimator::model`]).
//! The stage around them ([`crate::pipeline`]'s depth step) asks [`estimator`] for the one the
//! options name, so that an estimator is added here without touching the stages that read the maps.

use super::cnn::{CnnDepthError, cnn_depth};
use super::{DepthMap, DepthMethod, DepthOptions, DepthScratch, depth_from_focus_in};
use crate::domain::frame::{Frame, FrameError, View};
use crate::domain::optics::Optics;
use crate::learned::{LearnedError, Model, ModelRole, ModelUse, Models};
use std::sync::Arc;

/// One view's stack as an estimator reads it: `frame_at(k)` decodes frame k (an estimator decodes
/// each frame once); `cancelled()` is polled between frames.
pub struct ViewStack<'a> {
    pub optics: &'a Optics,
    pub view: &'a View,
    pub options: &'a DepthOptions,
    pub frame_at: &'a (dyn Fn(usize) -> Result<Frame, FrameError> + Sync),
    pub cancelled: &'a (dyn Fn() -> bool + Sync),
}

/// A view's depth-map estimator.
pub trait DepthEstimator: Sync {
    /// The learned model behind the maps, for the report (None: a classical rule).
    fn model(&self) -> Option<&ModelUse>;
    /// The view's depth map; Ok(None): cancelled. `scratch` is the caller's, kept from view to
    /// view.
    fn estimate(&self, stack: &ViewStack, scratch: &mut DepthScratch) -> Result<Option<Estimate>, CnnDepthError>;
}

/// One view's map, and the time a learned model took of it (for the report's stage parts).
pub struct Estimate {
    pub map: DepthMap,
    pub learned: std::time::Duration,
}

/// The classical depth from focus ([`depth_from_focus_in`]).
pub struct Classical;

impl DepthEstimator for Classical {
    fn model(&self) -> Option<&ModelUse> {
        None
    }

    fn estimate(&self, stack: &ViewStack, scratch: &mut DepthScratch) -> Result<Option<Estimate>, CnnDepthError> {
        scratch.keep_frames = false;
        let map =
            depth_from_focus_in(scratch, stack.optics, stack.view, stack.options, stack.frame_at, stack.cancelled)?;
        Ok(map.map(|map| Estimate { map, learned: std::time::Duration::ZERO }))
    }
}

/// The seed's U-Nets ([`cnn_depth`]) at the pixels the classical measure trusts: the classical
/// pass keeps the frames it decoded and the nets read those, so each frame is decoded once.
pub struct Cnn {
    pub model: Arc<Model>,
}

impl DepthEstimator for Cnn {
    fn model(&self) -> Option<&ModelUse> {
        Some(&self.model.identity)
    }

    fn estimate(&self, stack: &ViewStack, scratch: &mut DepthScratch) -> Result<Option<Estimate>, CnnDepthError> {
        scratch.keep_frames = true;
        let classical =
            depth_from_focus_in(scratch, stack.optics, stack.view, stack.options, stack.frame_at, stack.cancelled);
        scratch.keep_frames = false;
        let Some(mut map) = classical? else { return Ok(None) };
        let mut kept = std::mem::take(&mut scratch.kept_frames);
        let started = std::time::Instant::now();
        let done = cnn_depth(
            &self.model,
            stack.optics,
            stack.view,
            |k| match kept.get_mut(k).and_then(Option::take) {
                Some(frame) => Ok(frame),
                // Not kept (never, as the classical pass reads every frame once): decoded again.
                None => (stack.frame_at)(k),
            },
            stack.cancelled,
            &mut map,
        );
        let learned = started.elapsed();
        kept.clear();
        scratch.kept_frames = kept;
        Ok(done?.then_some(Estimate { map, learned }))
    }
}

/// The estimator `options` name, with its model from `models`.
pub fn estimator(options: &DepthOptions, models: &Models) -> Result<Box<dyn DepthEstimator>, LearnedError> {
    Ok(match options.method {
        DepthMethod::Classic => Box::new(Classical),
        DepthMethod::Cnn => Box::new(Cnn { model: models.get(ModelRole::Depth, options.model.as_deref())? }),
    })
}
