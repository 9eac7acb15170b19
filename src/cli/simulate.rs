//! `crestscan simulate`: render a bundle with ground truth, or list the presets.

use anyhow::{Context, Result, bail};
use crestscan::sim;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct SimulateArgs {
    /// Preset name (see --list).
    #[arg(long, required_unless_present_any = ["list", "list_stations", "spec"])]
    preset: Option<String>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output directory (created).
    #[arg(long, required_unless_present_any = ["list", "list_stations", "print_spec"])]
    out: Option<PathBuf>,
    /// Print the presets, one per line: name, then a short description.
    #[arg(long)]
    list: bool,
    /// Print the stations --station takes, one per line: name, then a short description.
    #[arg(long)]
    list_stations: bool,
    /// Write only truth/truth.json (no rendering).
    #[arg(long)]
    truth_only: bool,
    /// Record the preset's part at another station: `random` (drawn by --station-seed from the
    /// ranges in docs/simulator.md) or a named one (see --list-stations).
    #[arg(long)]
    station: Option<String>,
    /// The seed a random station is drawn by [default: --seed].
    #[arg(long)]
    station_seed: Option<u64>,
    /// Print the simulation's whole specification (part, station, sensor, texture) as JSON
    /// instead of rendering.
    #[arg(long)]
    print_spec: bool,
    /// Render this specification (JSON, as --print-spec writes it) instead of a preset's.
    #[arg(long, conflicts_with = "preset")]
    spec: Option<PathBuf>,
    /// Place the same part again: the encoders' errors and the sensor's noise drawn by this seed,
    /// the part and its texture by --seed (a master's repeat runs in a qualification study).
    #[arg(long)]
    placement_seed: Option<u64>,
    /// Also write the part's calibration certificate here (CMM JSON: every thread's height per 1°
    /// bin from the truth, with noise of the stated uncertainty), as a master's certificate.
    #[arg(long)]
    certificate: Option<PathBuf>,
    /// The certificate's expanded uncertainty (k = 2), µm: stated in it and drawn as its noise.
    #[arg(long, default_value_t = 2.0)]
    certificate_uncertainty_um: f64,
    /// Render every frame this much further along the camera's axis than the manifest declares,
    /// mm: a station refocused after its qualification (for drift checks).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    focus_drift_mm: f64,
    /// No progress bar (it is drawn only on a terminal in any case).
    #[arg(long)]
    quiet: bool,
}

impl SimulateArgs {
    pub fn run(self) -> Result<()> {
        let Self {
            preset,
            seed,
            out,
            list,
            list_stations,
            truth_only,
            station,
            station_seed,
            print_spec,
            spec: spec_file,
            placement_seed,
            certificate,
            certificate_uncertainty_um,
            focus_drift_mm,
            quiet,
        } = self;
        if !(focus_drift_mm.abs() <= 5.0) {
            bail!("--focus-drift-mm: {focus_drift_mm} is not within ±5 mm");
        }
        if !(certificate_uncertainty_um > 0.0 && certificate_uncertainty_um <= 100.0) {
            bail!("--certificate-uncertainty-um: {certificate_uncertainty_um} is not within (0, 100] µm");
        }
        let placement = placement_seed.unwrap_or(seed);
        if list {
            for p in sim::PRESETS {
                println!("{}\t{}", p.name, p.description);
            }
            return Ok(());
        }
        if list_stations {
            println!("random\tdrawn by --station-seed from the ranges in docs/simulator.md (Stations)");
            for (name, description) in sim::station::NAMED {
                println!("{name}\t{description}");
            }
            return Ok(());
        }
        let spec = match (&preset, spec_file) {
            (_, Some(path)) => {
                let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
                serde_json::from_str::<sim::SimSpec>(&text)
                    .with_context(|| format!("{}: not a simulation spec", path.display()))?
            }
            (Some(name), None) => sim::preset(name).with_context(|| {
                let names: Vec<_> = sim::PRESETS.iter().map(|p| p.name).collect();
                format!("unknown preset {name:?}; presets: {}", names.join(", "))
            })?,
            (None, None) => bail!("--preset or --spec is required"),
        };
        let name = spec.name.clone();
        let spec = match station {
            None => spec,
            Some(station) => {
                let radius = spec.part.pipe_od_mm / 2.0;
                let span = sim::station::z_span_mm(&spec);
                let Some(s) = sim::station::station(&station, station_seed.unwrap_or(seed), radius, span) else {
                    let names: Vec<_> = sim::station::NAMED.iter().map(|n| n.0).collect();
                    bail!("unknown station {station:?}; stations: random, {}", names.join(", "));
                };
                let spec = sim::station::at_station(&spec, &s);
                eprintln!("{}", spec.station.as_ref().expect("at a station").summary());
                spec
            }
        };
        let spec = sim::SimSpec { focus_drift_mm, ..spec };
        if print_spec {
            println!("{}", serde_json::to_string_pretty(&spec)?);
            return Ok(());
        }
        let Some(out) = out else { bail!("--out is required") };
        if let Some(path) = &certificate {
            let cert = sim::certificate(&spec.truth_placed(seed, placement), 1e-3 * certificate_uncertainty_um, seed);
            std::fs::write(path, serde_json::to_vec_pretty(&cert)?)
                .with_context(|| format!("--certificate: writing {}", path.display()))?;
        }
        if truth_only {
            let truth = sim::write_truth_placed(&spec, seed, placement, &out)?;
            println!("{}: {}", truth.verdict.as_str(), truth.reasons.join(" | "));
            return Ok(());
        }
        let bar = super::progress::bar((spec.views.len() * spec.offsets_mm.len()) as u64, "simulate", quiet);
        bar.set_message("frames");
        let summary = sim::simulate_placed(&spec, seed, placement, &out, &|_done| bar.inc(1));
        bar.finish_and_clear();
        let summary = summary.with_context(|| format!("simulating {name}"))?;
        println!(
            "{name} seed {seed}{}: {} frames, {} files, {:.1} MB in {:.1} s → {}; truth verdict {}",
            placement_seed.map(|p| format!(" placement {p}")).unwrap_or_default(),
            summary.frames,
            summary.files,
            summary.bytes as f64 / 1e6,
            summary.seconds,
            out.display(),
            summary.verdict.as_str()
        );
        Ok(())
    }
}
