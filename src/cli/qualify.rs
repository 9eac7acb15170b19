//! `crestscan qualify`: a station's qualification study (ISO 15530-3) without the service — each
//! master's runs inspected with the classical heights, compared with its certificate, and the
//! station's correction, uncertainty and gauge figures written as the JSON `inspect
//! --qualification` applies.

use super::open_bundle;
use anyhow::{Context, Result, bail};
use crestscan::bundle::OpenOptions;
use crestscan::eval::qualify::{self, Certificate, MasterRuns};
use crestscan::pipeline::{self, PipelineOptions, profile::Correction};
use sha2::Digest;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

#[derive(clap::Args)]
pub struct QualifyArgs {
    /// The station's name (what bundles and submissions name it by).
    #[arg(long)]
    station: String,
    /// A master's runs: a folder of bundles (each a folder with manifest.json, or an archive), or
    /// one bundle. Repeat for each master, each followed by its --certificate.
    #[arg(long, required = true)]
    master: Vec<PathBuf>,
    /// The master's calibration certificate (CMM JSON or CSV stating instrument, measured_at and
    /// uncertainty_mm), in the order of --master.
    #[arg(long, required = true)]
    certificate: Vec<PathBuf>,
    /// Until when the qualification holds (RFC 3339), if it expires.
    #[arg(long)]
    valid_until: Option<String>,
    /// Write the qualification here (JSON).
    #[arg(long)]
    out: PathBuf,
}

/// The bundles of a master: the folder itself when it is one, else its entries that are.
fn runs_of(dir: &Path) -> Result<Vec<PathBuf>> {
    if dir.join("manifest.json").is_file() || dir.is_file() {
        return Ok(vec![dir.to_path_buf()]);
    }
    let mut runs: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("--master {}: not a bundle nor a folder of bundles", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.join("manifest.json").is_file()
                || p.extension().is_some_and(|x| x == "zip" || x == "tar" || x == "gz" || x == "tgz")
        })
        .collect();
    runs.sort();
    if runs.is_empty() {
        bail!("--master {}: holds no bundle (folders with manifest.json, or archives)", dir.display());
    }
    Ok(runs)
}

/// The heights a study or a check reads: the classical ones, no learned correction.
fn classical() -> PipelineOptions {
    PipelineOptions {
        profile: crestscan::pipeline::profile::ProfileOptions { correction: Correction::Off, ..Default::default() },
        ..Default::default()
    }
}

#[derive(clap::Args)]
pub struct CheckArgs {
    /// The station's qualification (what `crestscan qualify` writes).
    #[arg(long)]
    qualification: PathBuf,
    /// The master's calibration certificate.
    #[arg(long)]
    certificate: PathBuf,
    /// The master's serial as the qualification names it [default: the bundles' `part.serial`,
    /// else the qualification's only master].
    #[arg(long)]
    master: Option<String>,
    /// The chart so far (what an earlier --chart wrote), continued by these runs.
    #[arg(long)]
    history: Option<PathBuf>,
    /// Write the chart, these runs appended, here (JSON).
    #[arg(long)]
    chart: Option<PathBuf>,
    /// The master's check runs, in the order they were made: bundles (folders or archives), or
    /// folders of them.
    #[arg(required = true)]
    runs: Vec<PathBuf>,
}

/// A chart as `station check` keeps it between calls.
#[derive(serde::Serialize, serde::Deserialize, Default)]
struct Chart {
    study: String,
    checks: Vec<ChartedRun>,
}

#[derive(serde::Serialize, serde::Deserialize)]
struct ChartedRun {
    run: String,
    master: String,
    points: Vec<crestscan::domain::control::ChartPoint>,
    violation: Option<crestscan::domain::control::Violation>,
}

impl CheckArgs {
    /// Charts each run; an error (exit 1) for runs that cannot be charted, exit 3 when one breaks
    /// a rule.
    pub fn run(self) -> Result<()> {
        use crestscan::domain::control::judge;
        let read = |p: &Path, flag: &str| std::fs::read(p).with_context(|| format!("--{flag} {}", p.display()));
        let q: crestscan::domain::qualification::Qualification =
            serde_json::from_slice(&read(&self.qualification, "qualification")?)
                .with_context(|| format!("--qualification {}: not a qualification", self.qualification.display()))?;
        let certificate = Certificate::parse(&read(&self.certificate, "certificate")?)
            .map_err(|e| anyhow::anyhow!("--certificate {}: {e}", self.certificate.display()))?;
        let mut chart = match &self.history {
            Some(p) => serde_json::from_slice::<Chart>(&read(p, "history")?)
                .with_context(|| format!("--history {}: not a chart `--chart` wrote", p.display()))?,
            None => Chart { study: q.study.clone(), checks: Vec::new() },
        };
        if chart.study != q.study {
            bail!(
                "--history is the chart of study {}, not of {}: a new study starts a new chart",
                chart.study,
                q.study
            );
        }
        let mut broke = false;
        for dir in &self.runs {
            for run in runs_of(dir)? {
                let bundle = open_bundle(&run, OpenOptions::default())?;
                let named = |s: &String| q.masters.iter().any(|m| &m.serial == s);
                let serial = match (&self.master, &bundle.part.serial) {
                    (Some(s), _) => s.clone(),
                    (None, Some(s)) if named(s) => s.clone(),
                    _ if q.masters.len() == 1 => q.masters[0].serial.clone(),
                    _ => bail!(
                        "{}: its part.serial names none of the study's masters ({}): say which with --master",
                        run.display(),
                        q.masters.iter().map(|m| m.serial.as_str()).collect::<Vec<_>>().join(", ")
                    ),
                };
                let inspection = pipeline::inspect(&bundle, &classical(), &|_, _| {}, &AtomicBool::new(false))
                    .with_context(|| format!("inspecting {}", run.display()))?
                    .context("cancelled")?;
                let name = run.display().to_string();
                let points = qualify::check(&q, &serial, &certificate, &name, &inspection.report)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", run.display()))?;
                let history: Vec<&[crestscan::domain::control::ChartPoint]> =
                    chart.checks.iter().filter(|c| c.master == serial).map(|c| c.points.as_slice()).collect();
                let violation = judge(&q.control, &serial, &history, &points);
                let readings: Vec<String> = points
                    .iter()
                    .map(|p| format!("{} {:.1} µm ({:+.2}σ)", p.statistic.describe(), p.value_um, p.z))
                    .collect();
                println!(
                    "check {} {}: {}; {}",
                    chart.checks.len() + 1,
                    name,
                    readings.join(", "),
                    violation.as_ref().map_or("in control".into(), |v| format!("BROKE {}", v.description))
                );
                broke |= violation.is_some();
                chart.checks.push(ChartedRun { run: name, master: serial, points, violation });
            }
        }
        if let Some(out) = &self.chart {
            std::fs::write(out, serde_json::to_vec_pretty(&chart)?)
                .with_context(|| format!("--chart {}", out.display()))?;
        }
        if broke {
            eprintln!("station {}: a check broke a rule; suspend it until it is requalified", q.station);
            use std::io::Write;
            let _ = std::io::stdout().flush();
            std::process::exit(3);
        }
        Ok(())
    }
}

impl QualifyArgs {
    pub fn run(self) -> Result<()> {
        let Self { station, master, certificate, valid_until, out } = self;
        if master.len() != certificate.len() {
            bail!(
                "{} --master but {} --certificate: give each master its certificate",
                master.len(),
                certificate.len()
            );
        }
        use crestscan::domain::text;
        text::check(&station, text::STATION_NAME_CHARS).map_err(|e| anyhow::anyhow!("--station {e}"))?;
        let options = classical();
        let mut hash = sha2::Sha256::new();
        let mut certificates = Vec::new();
        for path in &certificate {
            let bytes = std::fs::read(path).with_context(|| format!("--certificate {}", path.display()))?;
            hash.update(&bytes);
            certificates.push(
                Certificate::parse(&bytes).map_err(|e| anyhow::anyhow!("--certificate {}: {e}", path.display()))?,
            );
        }
        let mut reports = Vec::new();
        for dir in &master {
            let mut runs = Vec::new();
            for run in runs_of(dir)? {
                let bundle = open_bundle(&run, OpenOptions::default())?;
                // The manifest as read (a folder's or an archive's), so the id covers every run.
                hash.update(serde_json::to_vec(&bundle.manifest)?);
                let inspection = pipeline::inspect(&bundle, &options, &|_, _| {}, &AtomicBool::new(false))
                    .with_context(|| format!("inspecting {}", run.display()))?
                    .context("cancelled")?;
                let serial = bundle.part.serial.clone();
                runs.push((run.display().to_string(), serial, inspection.report));
                eprintln!("qualify: inspected {}", run.display());
            }
            reports.push(runs);
        }
        let masters: Vec<MasterRuns> = reports
            .iter()
            .zip(&master)
            .zip(&certificates)
            .map(|((runs, dir), cert)| MasterRuns {
                serial: runs
                    .first()
                    .and_then(|r| r.1.clone())
                    .unwrap_or_else(|| dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()),
                certificate: cert,
                runs: runs.iter().map(|(id, _, r)| (id.clone(), r)).collect(),
            })
            .collect();
        let study_id = format!("study-{}", &hex::encode(hash.finalize())[..12]);
        let q = qualify::study(&station, &study_id, &masters, 2.0, valid_until).map_err(|e| anyhow::anyhow!("{e}"))?;
        std::fs::write(&out, serde_json::to_vec_pretty(&q)?).with_context(|| format!("--out {}", out.display()))?;
        println!(
            "station {}: {} ({} master(s), {} runs); heights {:.1} → {:.1} µm RMS (held out, {}); U = {:.1} µm \
             (u_cal {:.1}, u_p {:.1}, u_b {:.1}, u_w {:.1}{}); Cg min {}, Cgk min {}, %GRR {} of the tolerance, ndc {} → {}",
            q.station,
            q.correction.model.as_str(),
            q.masters.len(),
            q.masters.iter().map(|m| m.runs).sum::<usize>(),
            q.rms_before_um,
            q.rms_after_um,
            q.selection.method,
            q.uncertainty.expanded_um,
            q.uncertainty.u_cal_um,
            q.uncertainty.u_p_um,
            q.uncertainty.u_b_um,
            q.uncertainty.u_w_um,
            if q.uncertainty.u_w_measured { "" } else { ", not measured: one master" },
            fmt(q.gauge.cg_min),
            fmt(q.gauge.cgk_min),
            fmt(q.gauge.grr_percent_tolerance),
            fmt(q.gauge.ndc),
            out.display()
        );
        Ok(())
    }
}

fn fmt(v: Option<f64>) -> String {
    v.map_or("–".into(), |v| format!("{v:.2}"))
}
