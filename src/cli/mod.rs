use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use crestscan::problem::ErrorCode;
use crestscan::bundle::{Bundle, FrameCheck, OpenOptions};
use crestscan::pipeline::{self, PipelineOptions};
use crestscan::domain::rules::ArcRule;
use crestscan::domain::thread::ConnectionTable;
use crestscan::{export::png, sim};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

#[derive(Parser)]
#[command(name = "crestscan", version, about = "Thread geometry from focal stacks, and API 5B black-crest acceptance")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The depth stage's options `inspect` and `bench` take.
#[derive(Args, Debug)]
struct DepthArgs {
    /// Estimate depth on every Nth pixel row across the arc (1: every row; the focus measure
    /// sees every row either way).
    #[arg(long, default_value_t = crestscan::pipeline::depth::DepthOptions::default().row_step as u16,
          value_parser = clap::value_parser!(u16).range(1..))]
    depth_row_step: u16,
    /// Half size of the small focus box that decides, at a steep edge, which surface a pixel
    /// shows (0: none: an eighth or so faster, with crest edges moved by up to the big box's
    /// half size; README, Pipeline, step 1).
    #[arg(long, default_value_t = crestscan::pipeline::depth::DepthOptions::default().edge_window_radius_px as u16)]
    depth_edge_window: u16,
}

impl From<DepthArgs> for crestscan::pipeline::depth::DepthOptions {
    fn from(args: DepthArgs) -> Self {
        Self {
            row_step: args.depth_row_step.into(),
            edge_window_radius_px: args.depth_edge_window.into(),
            ..Default::default()
        }
    }
}

#[derive(Subcommand)]
enum Command {
    /// Render a simulated focal-stack bundle with ground truth (truth/).
    Simulate {
        /// Preset name (see --list).
        #[arg(long, required_unless_present = "list")]
        preset: Option<String>,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Output directory (created).
        #[arg(long, required_unless_present = "list")]
        out: Option<PathBuf>,
        /// Print the presets, one per line: name, then a short description.
        #[arg(long)]
        list: bool,
        /// Write only truth/truth.json (no rendering).
        #[arg(long)]
        truth_only: bool,
    },
    /// Inspect a bundle (directory, .zip or .tar): thread heights, black crests, the 5B verdict.
    Inspect {
        bundle: PathBuf,
        /// Write report.json, height-map.png, all-in-focus.png, mesh.ply, mesh.stl and mesh.glb here.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print the report as JSON instead of the summary.
        #[arg(long)]
        json: bool,
        /// How the buttress 25% limit applies.
        #[arg(long, value_enum, default_value_t = ArcRuleArg::PerThread)]
        arc_rule: ArcRuleArg,
        /// Report each 1° bin's height as the trimmed mean (the middle half or so) of the 2N + 1
        /// bins centred on it along the helix (0: each bin's own fit, noisier; a dent of a degree
        /// or two is trimmed away, one of a few degrees flattened).
        #[arg(long, default_value_t = crestscan::pipeline::profile::ProfileOptions::default().height_window_half_bins)]
        height_window_half_bins: usize,
        #[command(flatten)]
        depth: DepthArgs,
    },
    /// Run a benchmark suite: render its cases (cached in --work), inspect, compare with truth.
    Bench {
        /// accuracy: the suite the targets are read on (its own seeds); holdout: the defect
        /// presets again with other seeds.
        #[arg(long, value_enum, default_value_t = SuiteArg::Accuracy)]
        suite: SuiteArg,
        /// Where renderings are cached [default: out/bench for accuracy, out/holdout for holdout].
        #[arg(long)]
        work: Option<PathBuf>,
        /// Only these cases of the suite (comma-separated): a preset (all its seeds) or
        /// preset-seed, e.g. bc-polished-3.
        #[arg(long, value_delimiter = ',')]
        only: Vec<String>,
        /// Also write the results as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Time each case this many times (decode and inspection alternating) and report the
        /// medians: single timings on a shared machine scatter by tens of percent.
        #[arg(long, default_value_t = 1)]
        repeat: usize,
        #[command(flatten)]
        depth: DepthArgs,
    },
    /// Compare an inspection report with a simulated bundle's truth/truth.json.
    Compare { report: PathBuf, truth: PathBuf },
    /// Validate a bundle (directory, .zip or .tar) without inspecting it.
    Validate {
        bundle: PathBuf,
        /// Decode every frame completely, not only its header.
        #[arg(long)]
        decode: bool,
    },
    /// Print the API 5B connection table.
    Connections {
        #[arg(long)]
        json: bool,
    },
    /// Run the HTTP service (REST API, job queue, workers). Settings: flags > CRESTSCAN_* > config file > defaults.
    Serve(ServeArgs),
    /// Print the OpenAPI document of the HTTP API (JSON).
    Openapi,
    /// Exit 0 when a local service answers /healthz (for container health checks; no curl needed).
    Healthcheck {
        /// The service's address [default: CRESTSCAN_BIND's port on 127.0.0.1, else 127.0.0.1:8080].
        #[arg(long)]
        addr: Option<std::net::SocketAddr>,
    },
}

fn healthcheck(addr: Option<std::net::SocketAddr>) -> Result<()> {
    use std::io::{Read, Write};
    let addr = addr.unwrap_or_else(|| {
        let port = std::env::var("CRESTSCAN_BIND")
            .ok()
            .and_then(|b| b.parse::<std::net::SocketAddr>().ok())
            .map_or(8080, |a| a.port());
        std::net::SocketAddr::from(([127, 0, 0, 1], port))
    });
    let timeout = std::time::Duration::from_secs(3);
    let mut stream =
        std::net::TcpStream::connect_timeout(&addr, timeout).with_context(|| format!("connecting to {addr}"))?;
    stream.set_read_timeout(Some(timeout))?;
    write!(stream, "GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n")?;
    let mut head = [0u8; 12];
    stream.read_exact(&mut head)?;
    if &head[9..12] != b"200" {
        bail!("{addr}/healthz answered {}", String::from_utf8_lossy(&head));
    }
    Ok(())
}

#[derive(clap::Args)]
struct ServeArgs {
    /// TOML file with any of the settings below (snake_case keys).
    #[arg(long, env = "CRESTSCAN_CONFIG")]
    config: Option<PathBuf>,
    /// Listen address [default: 127.0.0.1:8080].
    #[arg(long, env = "CRESTSCAN_BIND")]
    bind: Option<std::net::SocketAddr>,
    /// Database, uploads and temporaries [default: ./crestscan-data].
    #[arg(long, env = "CRESTSCAN_DATA_DIR")]
    data_dir: Option<PathBuf>,
    /// Inspections run at once [default: 1; each uses every core].
    #[arg(long, env = "CRESTSCAN_WORKERS")]
    workers: Option<usize>,
    /// Compute threads for the pipeline [default: 0 = one per core].
    #[arg(long, env = "CRESTSCAN_COMPUTE_THREADS")]
    compute_threads: Option<usize>,
    /// Largest upload in MiB [default: 4096].
    #[arg(long, env = "CRESTSCAN_MAX_UPLOAD_MB")]
    max_upload_mb: Option<u64>,
    /// Job lease in seconds [default: 30].
    #[arg(long, env = "CRESTSCAN_LEASE_SECONDS")]
    lease_seconds: Option<f64>,
    /// Heartbeat interval in seconds [default: 2].
    #[arg(long, env = "CRESTSCAN_HEARTBEAT_SECONDS")]
    heartbeat_seconds: Option<f64>,
    /// Claims before a job is failed [default: 3].
    #[arg(long, env = "CRESTSCAN_MAX_ATTEMPTS")]
    max_attempts: Option<u32>,
    /// Seconds running jobs get to finish at shutdown [default: 30].
    #[arg(long, env = "CRESTSCAN_SHUTDOWN_GRACE_SECONDS")]
    shutdown_grace_seconds: Option<f64>,
    /// Idle workers poll this often, in ms [default: 500].
    #[arg(long, env = "CRESTSCAN_POLL_INTERVAL_MS")]
    poll_interval_ms: Option<u64>,
    /// Days uploads of finished inspections are kept; 0 keeps them [default: 30].
    #[arg(long, env = "CRESTSCAN_UPLOAD_RETENTION_DAYS")]
    upload_retention_days: Option<f64>,
    /// Log filter [default: info].
    #[arg(long, env = "CRESTSCAN_LOG")]
    log: Option<String>,
}

impl ServeArgs {
    fn settings(self) -> Result<crestscan::service::config::Settings> {
        let mut s = match &self.config {
            Some(path) => crestscan::service::config::Settings::from_file(path)?,
            None => crestscan::service::config::Settings::default(),
        };
        macro_rules! set {
            ($($field:ident),*) => { $( if let Some(v) = self.$field { s.$field = v; } )* };
        }
        set!(
            bind,
            data_dir,
            workers,
            compute_threads,
            max_upload_mb,
            lease_seconds,
            heartbeat_seconds,
            max_attempts,
            shutdown_grace_seconds,
            poll_interval_ms,
            upload_retention_days,
            log
        );
        s.validate()?;
        Ok(s)
    }
}

fn serve(args: ServeArgs) -> Result<()> {
    let settings = args.settings()?;
    crestscan::service::telemetry::init_logging(&settings.log);
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    runtime.block_on(async move {
        let app = crestscan::service::startup::Application::build(settings.clone()).await?;
        // One line on stdout that scripts (and the tests) read to find the port.
        println!("crestscan listening on http://{}", app.address());
        tracing::info!(address = %app.address(), data_dir = %settings.data_dir.display(), workers = settings.workers, "serving");
        app.run_until(crestscan::service::startup::shutdown_signal()).await?;
        Ok(())
    })
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SuiteArg {
    Accuracy,
    Holdout,
}

impl From<SuiteArg> for crestscan::eval::Suite {
    fn from(s: SuiteArg) -> Self {
        match s {
            SuiteArg::Accuracy => Self::Accuracy,
            SuiteArg::Holdout => Self::Holdout,
        }
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ArcRuleArg {
    PerThread,
    Combined,
}

/// A command whose output is piped into a reader that stops early (`crestscan inspect B | head`)
/// ends as other command-line tools do, by SIGPIPE, rather than panicking in `println!`. Rust
/// ignores the signal so that a write to a closed socket returns an error instead: the commands
/// that talk over sockets (`serve`, `healthcheck`) keep that.
fn stop_quietly_on_closed_stdout() {
    #[cfg(unix)]
    // SAFETY: restores the default disposition of one signal before any thread is started.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

pub fn main() -> Result<()> {
    let cli = Cli::parse();
    if !matches!(cli.command, Command::Serve(_) | Command::Healthcheck { .. }) {
        stop_quietly_on_closed_stdout();
    }
    match cli.command {
        Command::Serve(args) => serve(args)?,
        Command::Healthcheck { addr } => healthcheck(addr)?,
        Command::Openapi => println!("{}", crestscan::service::api::openapi().to_pretty_json()?),
        Command::Simulate { preset, seed, out, list, truth_only } => {
            if list {
                for p in sim::PRESETS {
                    println!("{}\t{}", p.name, p.description);
                }
                return Ok(());
            }
            let (Some(name), Some(out)) = (preset, out) else { bail!("--preset and --out are required") };
            let Some(spec) = sim::preset(&name) else {
                let names: Vec<_> = sim::PRESETS.iter().map(|p| p.name).collect();
                bail!("unknown preset {name:?}; presets: {}", names.join(", "));
            };
            if truth_only {
                let truth = sim::write_truth(&spec, seed, &out)?;
                println!("{}: {}", truth.verdict.as_str(), truth.reasons.join(" | "));
                return Ok(());
            }
            let summary = sim::simulate(&spec, seed, &out).with_context(|| format!("simulating {name}"))?;
            println!(
                "{name} seed {seed}: {} frames, {} files, {:.1} MB in {:.1} s → {}; truth verdict {}",
                summary.frames,
                summary.files,
                summary.bytes as f64 / 1e6,
                summary.seconds,
                out.display(),
                summary.verdict.as_str()
            );
        }
        Command::Inspect { bundle, out, json, arc_rule, height_window_half_bins, depth } => {
            let table = ConnectionTable::api5b();
            let b = Bundle::open(&bundle, &table, OpenOptions::default())
                .map_err(|e| anyhow::anyhow!("[{}] {e}", e.code()))?;
            let options = PipelineOptions {
                arc_rule: match arc_rule {
                    ArcRuleArg::PerThread => ArcRule::PerThread,
                    ArcRuleArg::Combined => ArcRule::Combined,
                },
                profile: crestscan::pipeline::profile::ProfileOptions { height_window_half_bins },
                depth: depth.into(),
                ..Default::default()
            };
            let cancel = AtomicBool::new(false);
            let inspection = pipeline::inspect(&b, &options, &|_, _| {}, &cancel)?.context("cancelled")?;
            if let Some(dir) = &out {
                std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
                let report_path = dir.join("report.json");
                std::fs::write(&report_path, serde_json::to_vec_pretty(&inspection.report)?)
                    .with_context(|| format!("writing {}", report_path.display()))?;
                png::write_height_map(&inspection.map, &dir.join("height-map.png"))?;
                png::write_mosaic(&inspection.map, &dir.join("all-in-focus.png"))?;
                for (name, write) in [
                    (
                        "mesh.ply",
                        crestscan::export::ply::write
                            as fn(&crestscan::pipeline::mesh::Mesh, std::io::BufWriter<std::fs::File>) -> std::io::Result<()>,
                    ),
                    ("mesh.stl", crestscan::export::stl::write),
                    ("mesh.glb", crestscan::export::glb::write),
                ] {
                    let path = dir.join(name);
                    let file = std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
                    write(&inspection.mesh, std::io::BufWriter::new(file))
                        .with_context(|| format!("writing {}", path.display()))?;
                }
            }
            if json {
                println!("{}", serde_json::to_string_pretty(&inspection.report)?);
            } else {
                println!("{}", inspection.report.summary());
                if let Some(dir) = &out {
                    println!(
                        "  wrote report.json, height-map.png, all-in-focus.png, mesh.ply, mesh.stl and mesh.glb ({} vertices, {} triangles) to {}",
                        inspection.mesh.vertices.len(),
                        inspection.mesh.triangles.len(),
                        dir.display()
                    );
                }
            }
        }
        Command::Bench { suite, work, only, json, repeat, depth } => {
            let suite = crestscan::eval::Suite::from(suite);
            let work = work.unwrap_or_else(|| PathBuf::from(suite.default_work_dir()));
            if let Some(o) = only.iter().find(|o| !suite.cases().iter().any(|c| c.matches(o))) {
                let names: Vec<String> = suite.cases().iter().map(|c| c.name()).collect();
                bail!("--only {o:?} is no case of the {} suite; its cases: {}", suite.name(), names.join(", "));
            }
            let options = PipelineOptions { depth: depth.into(), ..Default::default() };
            let mut results = Vec::new();
            for case in suite.cases().iter().filter(|c| only.is_empty() || only.iter().any(|o| c.matches(o))) {
                eprintln!("bench: {} (seed {})", case.preset, case.seed);
                results.push(crestscan::eval::run_case(case, &work, repeat, &options)?);
            }
            println!("{}", crestscan::eval::table(&results));
            if let Some(path) = json {
                std::fs::write(&path, serde_json::to_vec_pretty(&results)?)?;
            }
        }
        Command::Compare { report, truth } => {
            let report: crestscan::pipeline::report::Report = serde_json::from_slice(&std::fs::read(&report)?)?;
            let truth: sim::Truth = serde_json::from_slice(&std::fs::read(&truth)?)?;
            println!("{}", serde_json::to_string_pretty(&crestscan::eval::compare(&report, &truth))?);
        }
        Command::Validate { bundle, decode } => {
            let table = ConnectionTable::api5b();
            let options = OpenOptions {
                frame_check: if decode { FrameCheck::Decode } else { FrameCheck::Headers },
                ..Default::default()
            };
            let b = Bundle::open(&bundle, &table, options).map_err(|e| anyhow::anyhow!("[{}] {e}", e.code()))?;
            println!(
                "{}: valid bundle v1; {} ({}), {} views, {} frames",
                bundle.display(),
                b.part.connection.as_deref().unwrap_or("custom thread"),
                b.part.family().as_str(),
                b.views.len(),
                b.frame_count()
            );
        }
        Command::Connections { json } => {
            let table = ConnectionTable::api5b();
            if json {
                println!("{}", serde_json::to_string_pretty(table.all())?);
            } else {
                println!("designation\tfamily\tOD mm\tpitch mm\theight mm\tLc mm\tL4 mm");
                for c in table.all() {
                    println!(
                        "{}\t{}\t{:.2}\t{:.3}\t{:.3}\t{:.2}\t{:.2}",
                        c.designation,
                        c.family.as_str(),
                        c.pipe_od_mm,
                        c.pitch_mm,
                        c.thread_height_mm,
                        c.lc_mm,
                        c.l4_mm
                    );
                }
            }
        }
    }
    Ok(())
}
