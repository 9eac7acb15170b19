//! Validation before any work: the part resolved from the table or its custom form, every view
//! and frame entry checked (offsets, paths, each frame's header), and the inspection's size
//! against the caps.

use super::*;
use crate::domain::station::{BENCHMARKED, MAX_OBJECT_PIXEL_MM, Station};

pub(super) fn thread_err(field: &str, message: impl Into<String>) -> BundleError {
    BundleError::Thread { field: field.into(), message: message.into() }
}

/// Connection table row, overridden field by field by `part.thread`.
pub fn resolve_part(part: &PartManifest, table: &ConnectionTable) -> Result<Part, BundleError> {
    let custom = part.thread.clone().unwrap_or_default();
    let row = match (&part.connection, &part.thread) {
        (Some(designation), _) => match table.get(designation) {
            Some(row) => Some(row),
            None if part.thread.is_some() => None,
            None => return Err(BundleError::UnknownConnection { designation: designation.clone() }),
        },
        (None, Some(_)) => None,
        (None, None) => {
            return Err(BundleError::Manifest {
                field: "part".into(),
                message: "needs a connection designation or a custom thread form".into(),
            });
        }
    };
    let need = |value: Option<f64>, from_row: Option<f64>, field: &'static str| {
        value
            .or(from_row)
            .ok_or_else(|| thread_err(field, "is required when part.connection is not in the connection table"))
    };
    let family = custom
        .family
        .or(row.map(|r| r.family))
        .ok_or_else(|| thread_err("family", "is required when part.connection is not in the connection table"))?;
    let pitch_mm = need(custom.pitch_mm, row.map(|r| r.pitch_mm), "pitch_mm")?;
    let height_mm = need(custom.thread_height_mm, row.map(|r| r.thread_height_mm), "thread_height_mm")?;
    let tolerance_mm = need(custom.height_tolerance_mm, row.map(|r| r.height_tolerance_mm), "height_tolerance_mm")?;
    let taper = need(custom.taper_on_diameter, row.map(|r| r.taper_on_diameter), "taper_on_diameter")?;
    let pipe_od_mm = need(custom.pipe_od_mm, row.map(|r| r.pipe_od_mm), "pipe_od_mm")?;
    let lc_mm = need(custom.lc_mm, row.map(|r| r.lc_mm), "lc_mm")?;
    for (field, value) in [("pipe_od_mm", pipe_od_mm), ("lc_mm", lc_mm)] {
        if !(value.is_finite() && value > 0.0) {
            return Err(thread_err(field, format!("must be a finite number > 0, got {value}")));
        }
    }
    let form_fields_given = custom.family.is_some()
        || custom.pitch_mm.is_some()
        || custom.thread_height_mm.is_some()
        || custom.height_tolerance_mm.is_some()
        || custom.taper_on_diameter.is_some()
        || custom.load_flank_deg.is_some()
        || custom.stab_flank_deg.is_some()
        || custom.crest_width_mm.is_some()
        || custom.flank_deg.is_some()
        || custom.root_truncation_mm.is_some();
    let form = match row {
        Some(r) if !form_fields_given => r.form().clone(),
        _ => build_form(family, pitch_mm, height_mm, tolerance_mm, taper, &custom)
            .map_err(|e| form_error_to_bundle(&e))?,
    };
    Ok(Part {
        serial: part.serial.clone(),
        connection: row.map(|r| r.designation.clone()).or_else(|| part.connection.clone()),
        form,
        pipe_od_mm,
        lc_mm,
        gauge: row.map(|r| r.gauge),
    })
}

pub(super) fn build_form(
    family: Family,
    pitch_mm: f64,
    height_mm: f64,
    tolerance_mm: f64,
    taper: f64,
    custom: &CustomThread,
) -> Result<ThreadForm, FormError> {
    match family {
        Family::Round => ThreadForm::round(
            pitch_mm,
            height_mm,
            tolerance_mm,
            taper,
            custom.flank_deg.unwrap_or(30.0),
            custom.root_truncation_mm,
        ),
        Family::Buttress => {
            let load = custom.load_flank_deg.unwrap_or(3.0);
            let stab = custom.stab_flank_deg.unwrap_or(10.0);
            let flanks = height_mm * (load.to_radians().tan() + stab.to_radians().tan());
            let crest_width_mm = custom.crest_width_mm.unwrap_or((pitch_mm - flanks) / 2.0);
            ThreadForm::new(
                family,
                pitch_mm,
                height_mm,
                tolerance_mm,
                taper,
                ProfileShape::Trapezoid { load_flank_deg: load, stab_flank_deg: stab, crest_width_mm },
            )
        }
    }
}

pub(super) fn form_error_to_bundle(e: &FormError) -> BundleError {
    let field = match e {
        FormError::NotPositive { field, .. }
        | FormError::Negative { field, .. }
        | FormError::OutOfRange { field, .. } => field.to_string(),
        FormError::DoesNotFit(_) => "thread_height_mm".to_string(),
    };
    thread_err(&field, e.to_string())
}

/// Bytes of a PNG read for its header: the signature and IHDR take 33, and ancillary chunks
/// before the first IDAT rarely take more.
const PNG_HEAD_BYTES: usize = 64 << 10;

/// A frame's format from its header. A PNG's comes from its first bytes, so its pixel data is
/// not held in memory; a PNG whose header chunks run past them, and every TIFF (whose directory
/// may sit anywhere), is read whole.
fn probe_header(source: &Source, file: &str) -> Result<FrameFormat, BundleError> {
    if !super::decode::is_tiff(file) {
        let head = source.read_head(file, PNG_HEAD_BYTES)?;
        match probe(file, &head) {
            Ok(format) => return Ok(format),
            Err(_) if head.len() == PNG_HEAD_BYTES => {}
            Err(e) => return Err(e),
        }
    }
    probe(file, &source.read(file)?)
}

pub(super) fn validate_views(
    manifest: &Manifest,
    source: &Source,
    check: FrameCheck,
) -> Result<Vec<View>, BundleError> {
    if manifest.views.is_empty() {
        return Err(BundleError::Manifest { field: "views".into(), message: "is empty".into() });
    }
    let mut ids = HashSet::new();
    let mut files = HashSet::new();
    let mut views = Vec::with_capacity(manifest.views.len());
    for (i, view) in manifest.views.iter().enumerate() {
        let at = |rest: &str| format!("views[{i}]{rest}");
        if view.id.is_empty() || view.id.contains(['/', '\\']) || view.id == "." || view.id == ".." {
            return Err(BundleError::Manifest {
                field: at(".id"),
                message: format!("{:?} must be a non-empty name without '/' or '\\'", view.id),
            });
        }
        if !ids.insert(view.id.as_str()) {
            return Err(BundleError::Manifest { field: at(".id"), message: format!("{:?} is used twice", view.id) });
        }
        let pose = &view.pose;
        // Bounds far outside any station, so that a typo (or 1e300) is named here instead of
        // overflowing a stage: two turns either way, and a kilometre.
        for (name, value, bound) in [
            ("angle_deg", pose.angle_deg, 720.0),
            ("axial_mm", pose.axial_mm, 1e6),
            ("lens_radius_mm", pose.lens_radius_mm, 1e6),
        ] {
            if !value.is_finite() {
                return Err(BundleError::Manifest {
                    field: at(&format!(".pose.{name}")),
                    message: format!("must be finite, got {value}"),
                });
            }
            if value.abs() > bound {
                return Err(BundleError::Manifest {
                    field: at(&format!(".pose.{name}")),
                    message: format!("{value} is outside ±{bound}"),
                });
            }
        }
        if pose.lens_radius_mm <= 0.0 {
            return Err(BundleError::Manifest {
                field: at(".pose.lens_radius_mm"),
                message: format!("must be > 0, got {}", pose.lens_radius_mm),
            });
        }
        if view.frames.len() < MIN_FRAMES {
            return Err(BundleError::TooFewFrames { field: at(".frames"), count: view.frames.len() });
        }
        for (k, frame) in view.frames.iter().enumerate() {
            let field = at(&format!(".frames[{k}].offset_mm"));
            if !frame.offset_mm.is_finite() {
                return Err(BundleError::Offsets {
                    field,
                    message: format!("must be finite, got {}", frame.offset_mm),
                });
            }
            if k > 0 {
                let prev = view.frames[k - 1].offset_mm;
                if frame.offset_mm == prev {
                    return Err(BundleError::Offsets {
                        field,
                        message: format!("duplicates the previous offset {prev} mm"),
                    });
                }
                if frame.offset_mm < prev {
                    return Err(BundleError::Offsets {
                        field,
                        message: format!("{} mm after {prev} mm: offsets must grow from near to far", frame.offset_mm),
                    });
                }
            }
            check_relative_path(&frame.file)
                .map_err(|message| BundleError::UnsafePath { path: frame.file.clone(), message })?;
            let lower = frame.file.to_ascii_lowercase();
            if !(lower.ends_with(".png") || lower.ends_with(".tif") || lower.ends_with(".tiff")) {
                return Err(BundleError::UnreadableFrame {
                    path: frame.file.clone(),
                    message: "frames must be .png, .tif or .tiff".into(),
                });
            }
            if lower.starts_with("truth/") {
                return Err(BundleError::UnsafePath {
                    path: frame.file.clone(),
                    message: "truth/ is ground truth and never read by inspection".into(),
                });
            }
            if !files.insert(frame.file.as_str()) {
                return Err(BundleError::Manifest {
                    field: at(&format!(".frames[{k}].file")),
                    message: format!("{:?} is listed twice", frame.file),
                });
            }
        }
        // Frame formats: every frame readable, one size, bit depth and colour type per view.
        let mut format: Option<(FrameFormat, &str)> = None;
        for frame in &view.frames {
            let this = match check {
                FrameCheck::Headers => probe_header(source, &frame.file)?,
                FrameCheck::Decode => {
                    let bytes = source.read(&frame.file)?;
                    let (probed, decoded) = (probe(&frame.file, &bytes)?, decode(&frame.file, &bytes)?);
                    debug_assert_eq!(decoded.width, probed.width);
                    probed
                }
            };
            match format {
                None => format = Some((this, frame.file.as_str())),
                Some((first, first_file)) if first != this => {
                    return Err(BundleError::InconsistentFrames {
                        path: frame.file.clone(),
                        message: format!(
                            "{}×{} {}-bit {} differs from {first_file} ({}×{} {}-bit {}) in view {:?}",
                            this.width,
                            this.height,
                            this.bit_depth,
                            channels_name(this.channels),
                            first.width,
                            first.height,
                            first.bit_depth,
                            channels_name(first.channels),
                            view.id
                        ),
                    });
                }
                Some(_) => {}
            }
        }
        let (format, _) = format.expect("at least MIN_FRAMES frames");
        views.push(View { id: view.id.clone(), pose: view.pose, frames: view.frames.clone(), format });
    }
    Ok(views)
}

/// Refuses a bundle whose inspection would need more memory than [`Limits`] allows: the focus
/// volume of a view, the depth maps of all views, and the grids over the surface the views cover.
/// (Caught here, a manifest with a mistyped pixel pitch or pose is an error that names the field;
/// caught by the allocator, it would end the process.)
pub(super) fn check_work(part: &Part, optics: &Optics, views: &[View], limits: Limits) -> Result<(), BundleError> {
    let too_large = |field: String, message: String| BundleError::InspectionTooLarge { field, message };
    let pixels = |v: &View| v.format.width as u64 * v.format.height as u64;
    for (i, view) in views.iter().enumerate() {
        let samples = pixels(view).saturating_mul(view.frames.len() as u64);
        if samples > limits.max_stack_samples {
            return Err(too_large(
                format!("views[{i}].frames"),
                format!(
                    "{} frames of {}×{} pixels are {samples} samples, more than the {} one view's focal \
                     stack may hold",
                    view.frames.len(),
                    view.format.width,
                    view.format.height,
                    limits.max_stack_samples
                ),
            ));
        }
    }
    let view_pixels: u64 = views.iter().map(pixels).fold(0, u64::saturating_add);
    if view_pixels > limits.max_view_pixels {
        return Err(too_large(
            "views".into(),
            format!(
                "{} views of {view_pixels} pixels in all (a frame each), more than the {} an inspection keeps \
                 depth maps for",
                views.len(),
                limits.max_view_pixels
            ),
        ));
    }
    let band = crate::domain::station::surface_pixels(optics, views, part.circumference_mm());
    let (surface, band_mm, frame_mm, lo, hi, pixel_mm) =
        (band.pixels, band.band_mm, band.frame_mm, band.lo, band.hi, band.pixel_mm);
    let axial = |i: usize| views[i].pose.axial_mm;
    if surface > limits.max_surface_pixels as f64 {
        // The culprit: a pose far from the others when the poses spread over more than a frame, a
        // custom pipe over twice the largest API 5B one (20 in, 508 mm), else the optics' scale.
        let field = if band.spread_mm > frame_mm {
            let mut by_axial: Vec<f64> = views.iter().map(|v| v.pose.axial_mm).collect();
            by_axial.sort_by(f64::total_cmp);
            let median = by_axial[by_axial.len() / 2];
            let outlier = if axial(hi) - median >= median - axial(lo) { hi } else { lo };
            format!("views[{outlier}].pose.axial_mm")
        } else if part.pipe_od_mm > 2.0 * 508.0 {
            "part.thread.pipe_od_mm".to_string()
        } else {
            "optics.pixel_pitch_um".to_string()
        };
        return Err(too_large(
            field,
            format!(
                "the views cover {band_mm:.3} mm along the axis (views[{lo}].pose.axial_mm {} to \
                 views[{hi}].pose.axial_mm {}, plus a frame's width) of the {:.1} mm circumference, in \
                 object pixels of {:.4} µm (optics.pixel_pitch_um over the magnification): {surface:.3e} \
                 pixels, more than the {} of the surface grids an inspection builds",
                axial(lo),
                axial(hi),
                part.circumference_mm(),
                pixel_mm * 1e3,
                limits.max_surface_pixels
            ),
        ));
    }
    Ok(())
}

pub(super) fn channels_name(channels: u8) -> &'static str {
    if channels == 1 { "gray" } else { "RGB" }
}

/// The fewest object pixels a pitch may span: the profile stage fits crest and root over windows
/// a fraction of a pitch wide.
const MIN_PIXELS_PER_PITCH: f64 = 10.0;
/// The widest frame step, in depths of field, at which a pixel's focus curve still has frames on
/// both shoulders of its peak (the depth stage locates the peak between them).
const MAX_FRAME_STEP_DOF: f64 = 2.0;

/// Refuses a station the method cannot measure at, whatever its accuracy elsewhere: a pixel too
/// coarse to resolve the thread's pitch, frames too far apart to sample a focus curve, or a stack
/// too short to bring the thread's roots and crests both into focus, or a pixel coarser than any
/// station class was benchmarked at. Stations inside these limits
/// but outside the measured envelope are inspected and flagged (`domain::station`).
pub(super) fn check_station(part: &Part, optics: &Optics, views: &[View]) -> Result<(), BundleError> {
    let out = |field: String, message: String| BundleError::StationOutOfRange { field, message };
    let station = Station::of(optics, views, part.pipe_od_mm / 2.0);
    let pitch_mm = part.form.pitch_mm;
    if station.object_pixel_mm * MIN_PIXELS_PER_PITCH > pitch_mm {
        return Err(out(
            "optics.pixel_pitch_um".into(),
            format!(
                "one pixel covers {:.3} mm of the part; the thread's {pitch_mm} mm pitch needs at least \
                 {MIN_PIXELS_PER_PITCH} pixels (each at most {:.3} mm)",
                station.object_pixel_mm,
                pitch_mm / MIN_PIXELS_PER_PITCH
            ),
        ));
    }
    if station.object_pixel_mm > MAX_OBJECT_PIXEL_MM {
        return Err(out(
            "optics.pixel_pitch_um".into(),
            format!(
                "one pixel covers {:.3} mm of the part, over {MAX_OBJECT_PIXEL_MM:.2} mm: beyond the coarsest station \
                 class measured (up to {:.2} mm, GET /v1/capabilities), nothing says how far off heights would be there",
                station.object_pixel_mm, BENCHMARKED.object_pixel_mm.1
            ),
        ));
    }
    for (i, view) in views.iter().enumerate() {
        let mut offsets: Vec<f64> = view.frames.iter().map(|f| f.offset_mm).collect();
        offsets.sort_by(f64::total_cmp);
        let widest = offsets.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
        if widest > MAX_FRAME_STEP_DOF * station.depth_of_field_mm {
            return Err(out(
                format!("views[{i}].frames"),
                format!(
                    "frames {widest:.3} mm apart, {:.1} depths of field ({:.3} mm at a blur of one pixel); a \
                     focus curve needs frames at most {MAX_FRAME_STEP_DOF} depths of field apart",
                    widest / station.depth_of_field_mm,
                    station.depth_of_field_mm
                ),
            ));
        }
        let span = offsets.last().copied().unwrap_or(0.0) - offsets.first().copied().unwrap_or(0.0);
        if span < part.form.height_mm {
            return Err(out(
                format!("views[{i}].frames"),
                format!(
                    "the focal stack spans {span:.3} mm of offset; the thread is {:.3} mm deep, so its roots and \
                     crests cannot both come into focus",
                    part.form.height_mm
                ),
            ));
        }
    }
    Ok(())
}
