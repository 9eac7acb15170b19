//! `crestscan station plan`: the station a camera and lens make for a connection — object pixel,
//! depth of field, the frame step and stack, and the views and rows that cover the whole Lc ring
//! with the overlap registration needs — and the class it falls in.

use anyhow::{Context, Result, bail};
use crestscan::domain::optics::{Optics, Projection};
use crestscan::domain::station::{BENCHMARKED, IN_FOCUS_BLUR_PX, MEASURED, Station};
use crestscan::domain::thread::ConnectionTable;

#[derive(clap::Subcommand)]
pub enum StationCommand {
    /// Plan a station for a connection from its camera and lens.
    Plan(PlanArgs),
    /// Chart a master's check runs against a qualification's control limits (Western Electric
    /// rules): each run's height bias and crest-cone radius in σ; exits 3 when one breaks a rule
    /// (the station has drifted: suspend it until requalified).
    Check(super::qualify::CheckArgs),
}

#[derive(clap::Args)]
pub struct PlanArgs {
    /// The API 5B designation (`crestscan connections` lists them).
    #[arg(long)]
    connection: String,
    /// The sensor's size in pixels, WxH (the rows span the arc, the columns the axis).
    #[arg(long)]
    sensor: String,
    /// The sensor's pixel pitch, µm (after any binning).
    #[arg(long)]
    pixel_um: f64,
    /// The lens's focal length, mm.
    #[arg(long)]
    lens_mm: f64,
    /// The lens's f-number.
    #[arg(long)]
    f_number: f64,
    /// The focus distance, lens to the part's surface, mm.
    #[arg(long)]
    distance_mm: f64,
}

/// The frame step as a share of the depth of field: the middle of the range the accuracy figures
/// were measured at.
const STEP_OF_DOF: f64 = 0.5;
/// How far the stack reaches beyond the thread's depth on each side, mm: the part's placement and
/// run-out (the encoders' radial bound in the simulator's stations is 0.3 mm; twice that).
const STACK_MARGIN_MM: f64 = 0.6;
/// The axial overlap of neighbouring rows of views, mm (two pitches of the coarsest thread).
const ROW_OVERLAP_MM: f64 = 10.0;

impl StationCommand {
    pub fn run(self) -> Result<()> {
        match self {
            StationCommand::Plan(args) => args.run(),
            StationCommand::Check(args) => args.run(),
        }
    }
}

impl PlanArgs {
    fn run(self) -> Result<()> {
        let table = ConnectionTable::api5b();
        let conn = table.get(&self.connection).with_context(|| {
            format!("--connection {:?}: not in the API 5B table (crestscan connections lists it)", self.connection)
        })?;
        let (w, h) = self
            .sensor
            .split_once(['x', 'X'])
            .and_then(|(w, h)| Some((w.trim().parse::<u32>().ok()?, h.trim().parse::<u32>().ok()?)))
            .filter(|(w, h)| (16..=20_000).contains(w) && (16..=20_000).contains(h))
            .with_context(|| format!("--sensor {:?}: give the size as WxH pixels, e.g. 1280x1024", self.sensor))?;
        for (name, v, lo, hi) in [
            ("--pixel-um", self.pixel_um, 0.5, 50.0),
            ("--lens-mm", self.lens_mm, 1.0, 2000.0),
            ("--f-number", self.f_number, 0.5, 256.0),
            ("--distance-mm", self.distance_mm, 1.0, 1e5),
        ] {
            if !(lo..=hi).contains(&v) {
                bail!("{name}: {v} is outside {lo}–{hi}");
            }
        }
        if self.distance_mm <= self.lens_mm {
            bail!(
                "--distance-mm: {} mm is inside the focal length ({} mm): nothing comes to focus",
                self.distance_mm,
                self.lens_mm
            );
        }
        let optics = Optics {
            projection: Projection::Perspective,
            focal_length_mm: Some(self.lens_mm),
            f_number: self.f_number,
            focus_distance_mm: self.distance_mm,
            pixel_pitch_um: self.pixel_um,
            principal_point_px: None,
            magnification: None,
        };
        let pixel_mm = optics.object_pixel_mm(self.distance_mm);
        let dof_mm = optics.depth_of_field_mm(IN_FOCUS_BLUR_PX);
        let form = conn.form();
        let radius_mm = conn.pipe_od_mm / 2.0;
        let step_mm = STEP_OF_DOF * dof_mm;
        let reach_mm = form.height_mm + dof_mm + 2.0 * STACK_MARGIN_MM;
        let frames = (reach_mm / step_mm).ceil() as usize + 1;
        // The rows span the arc; neighbours must overlap by what registration was measured with.
        let footprint_deg = (h as f64 * pixel_mm / radius_mm).to_degrees();
        let overlap_deg = MEASURED.overlap_deg.0.max(BENCHMARKED.overlap_deg.0);
        if footprint_deg <= overlap_deg {
            bail!(
                "a view spans {footprint_deg:.1}° of the ring, no more than the {overlap_deg}° overlap registration needs: a longer lens distance or a larger sensor"
            );
        }
        let views = (360.0 / (footprint_deg - overlap_deg)).ceil() as usize;
        let spacing_deg = 360.0 / views as f64;
        // The columns span the axis: from the end face to half a pitch past Lc, so that the crest
        // at Lc is seen whole.
        let field_z_mm = w as f64 * pixel_mm;
        let span_z_mm = conn.lc_mm + 0.5 * form.pitch_mm;
        let rows = if field_z_mm >= span_z_mm {
            1
        } else {
            ((span_z_mm - ROW_OVERLAP_MM) / (field_z_mm - ROW_OVERLAP_MM).max(1.0)).ceil() as usize
        };
        let station = Station {
            projection: Projection::Perspective,
            object_pixel_mm: pixel_mm,
            depth_of_field_mm: dof_mm,
            frame_step_mm: step_mm,
            frame_step_dof: STEP_OF_DOF,
            frames_per_view: frames,
            views: views * rows,
            axial_rows: rows,
            view_spacing_deg: Some(spacing_deg),
            overlap_deg: Some(footprint_deg - spacing_deg),
            frame_noise_percent: None,
            class: None,
            qualified_by: None,
        }
        .with_frame_noise(None);
        println!(
            "station for {} (pipe {:.2} mm, Lc {:.1} mm, thread height {:.3} mm):",
            conn.designation, conn.pipe_od_mm, conn.lc_mm, form.height_mm
        );
        println!("  object pixel      {:.1} µm at {:.0} mm", 1e3 * pixel_mm, self.distance_mm);
        println!("  depth of field    {:.3} mm ({:.0}% of the thread height)", dof_mm, 100.0 * dof_mm / form.height_mm);
        println!(
            "  frames            every {step_mm:.3} mm ({STEP_OF_DOF} of the depth of field), {frames} per view over {:.2} mm",
            step_mm * (frames - 1) as f64
        );
        println!(
            "  views             {views} around, {spacing_deg:.2}° apart, each {footprint_deg:.1}° of arc: overlap {:.1}°",
            footprint_deg - spacing_deg
        );
        println!(
            "  rows              {rows} (a view spans {field_z_mm:.1} mm axially; the ring to cover is {span_z_mm:.1} mm)"
        );
        println!("  U after a study   {}", predicted_u(station.class));
        match station.class {
            Some(class) => println!(
                "  class             {} (GET /v1/capabilities has the class's figures; qualify the station on masters before deciding with it: docs/service.md)",
                class.as_str()
            ),
            None => {
                let outside = station.outside(&BENCHMARKED);
                println!("  class             none: outside the benchmarked ranges ({})", outside.join("; "))
            }
        }
        Ok(())
    }
}

/// What the qualification benchmark measured of U at stations of `class`.
fn predicted_u(class: Option<crestscan::domain::station::StationClass>) -> String {
    use crestscan::domain::station::{QUALIFIED_U_UM, StationClass};
    let own = "this station's own study states its U (docs/benchmark.md#station-qualification)";
    let Some(class) = class else { return format!("no station like it was studied; {own}") };
    if class == StationClass::Standard {
        return format!(
            "not studied by the benchmark: the standard station's U without a study is in GET /v1/capabilities; {own}"
        );
    }
    let studied: Vec<(&str, f64)> =
        QUALIFIED_U_UM.iter().filter(|(c, _, _)| *c == class).map(|(_, s, u)| (*s, *u)).collect();
    match studied.as_slice() {
        [] => format!("no {} station was studied; {own}", class.as_str()),
        [(name, u)] => format!("{u:.1} µm (k = 2) at the one {} station studied ({name}); {own}", class.as_str()),
        many => {
            let (lo, hi) = many.iter().fold((f64::MAX, 0.0f64), |(lo, hi), (_, u)| (lo.min(*u), hi.max(*u)));
            let each: Vec<String> = many.iter().map(|(s, u)| format!("{s} {u:.1}")).collect();
            format!(
                "{lo:.1}–{hi:.1} µm (k = 2) at the {} {} stations studied ({}): set by each one's repeatability; {own}",
                many.len(),
                class.as_str(),
                each.join(", ")
            )
        }
    }
}
