//! The command line: one file per subcommand; each parses its own arguments and calls the library.

mod bench;
mod budget;
mod compare;
mod connections;
mod inspect;
mod keys;
mod migrate;
mod object_store;
mod pairs;
mod progress;
mod qualify;
mod serve;
mod simulate;
mod station;
mod validate;

use anyhow::Result;
use clap::{Args, Parser, Subcommand};
use crestscan::bundle::{Bundle, OpenOptions};
use crestscan::domain::thread::ConnectionTable;
use crestscan::pipeline::depth::DepthOptions;
use crestscan::pipeline::profile::{Correction, ProfileOptions};
use crestscan::problem::ErrorCode;
use std::path::Path;

#[derive(Parser)]
#[command(name = "crestscan", version, about = "Thread geometry from focal stacks, and API 5B black-crest acceptance")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a simulated focal-stack bundle with ground truth (truth/).
    Simulate(simulate::SimulateArgs),
    /// Inspect a bundle (directory, .zip or .tar): thread heights, black crests, the 5B verdict.
    Inspect(inspect::InspectArgs),
    /// Stations: plan one from a camera and lens for a connection.
    #[command(subcommand)]
    Station(station::StationCommand),
    /// Qualify a station (ISO 15530-3): masters' repeat runs against their certificates → the
    /// station's correction, uncertainty and gauge figures, as JSON `inspect --qualification` takes.
    Qualify(qualify::QualifyArgs),
    /// Run a benchmark suite: render its cases (cached in --work), inspect, compare with truth.
    Bench(bench::BenchArgs),
    /// Where a simulated bundle's height error enters along the pipeline: the bundle inspected
    /// with the true poses, depth maps and helix put in turn, each step measured against truth.
    Budget(budget::BudgetArgs),
    /// Compare an inspection report with a simulated bundle's truth/truth.json.
    Compare(compare::CompareArgs),
    /// Write the profile-correction MLP's training pairs of a bundle (JSON lines; docs/models.md).
    Pairs(pairs::PairsArgs),
    /// Validate a bundle (directory, .zip or .tar) without inspecting it.
    Validate(validate::ValidateArgs),
    /// Print the API 5B connection table.
    Connections(connections::ConnectionsArgs),
    /// Run the HTTP service (REST API, job queue, workers). Settings: flags > CRESTSCAN_* > config file > defaults.
    Serve(Box<serve::ServeArgs>),
    /// API keys of a service's data directory: create (the first admin key), list, revoke.
    Keys(keys::KeysArgs),
    /// Copy a data directory's uploaded bundles into an S3-compatible object store, resumable and
    /// verified, before serving it with --object-store.
    MigrateStore(migrate::MigrateStoreArgs),
    /// Print a new webhook signing secret (whsec_…, 32 random bytes) for a `[[webhooks]]`
    /// endpoint's `secrets` or `callback_secrets`, and for the receiver that verifies them.
    WebhookSecret,
    /// Print the OpenAPI document of the HTTP API (JSON), or the bundle manifest's JSON Schema.
    Openapi {
        /// The JSON Schema of a bundle's manifest.json instead (what `GET /v1/schemas/manifest` serves).
        #[arg(long)]
        manifest_schema: bool,
    },
    /// Exit 0 when a local service answers /healthz (for container health checks; no curl needed).
    Healthcheck {
        /// The service's address [default: CRESTSCAN_BIND's port on 127.0.0.1, else 127.0.0.1:8080].
        #[arg(long)]
        addr: Option<std::net::SocketAddr>,
    },
}

/// The learned parts' options `inspect` and `bench` take (docs/models.md).
#[derive(Args, Debug)]
struct LearnedArgs {
    /// Correct each bin's pitch of profile with the seed's MLP before its height is taken (needs
    /// ONNX Runtime: scripts/setup-onnxruntime); `auto` where the model's card says it helps the
    /// part's thread family at the station's pixels (docs/models.md).
    #[arg(long, value_enum, default_value_t = CorrectionArg::from(ProfileOptions::default().correction))]
    profile_correction: CorrectionArg,
    /// The correction model by name [default: the shipped one]; an installed one is
    /// `<models-dir>/<name>.onnx` with its card `<name>.json`.
    #[arg(long)]
    correction_model: Option<String>,
    /// Where installed models are looked for.
    #[arg(long, env = "CRESTSCAN_MODELS_DIR")]
    models_dir: Option<std::path::PathBuf>,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum CorrectionArg {
    On,
    Off,
    /// Where the model's card says it helps threads of the part's family at the station's pixel.
    Auto,
}

impl From<Correction> for CorrectionArg {
    fn from(c: Correction) -> Self {
        match c {
            Correction::On => CorrectionArg::On,
            Correction::Off => CorrectionArg::Off,
            Correction::Auto => CorrectionArg::Auto,
        }
    }
}

impl LearnedArgs {
    /// `profile` with these choices, and the models folder set for the process.
    fn apply(self, profile: ProfileOptions) -> ProfileOptions {
        crestscan::learned::set_installed_dir(self.models_dir);
        ProfileOptions {
            correction: match self.profile_correction {
                CorrectionArg::On => Correction::On,
                CorrectionArg::Off => Correction::Off,
                CorrectionArg::Auto => Correction::Auto,
            },
            correction_model: self.correction_model,
            ..profile
        }
    }
}

/// The depth stage's options `inspect` and `bench` take.
#[derive(Args, Debug)]
struct DepthArgs {
    /// Estimate depth on every Nth pixel row across the arc (1: every row; the focus measure
    /// sees every row either way).
    #[arg(long, default_value_t = DepthOptions::default().row_step as u16,
          value_parser = clap::value_parser!(u16).range(1..))]
    depth_row_step: u16,
    /// Half size of the small focus box that decides, at a steep edge, which surface a pixel
    /// shows (0: none: an eighth or so faster, with crest edges moved by up to the big box's
    /// half size; docs/pipeline.md, 1. Depth from focus).
    #[arg(long, default_value_t = DepthOptions::default().edge_window_radius_px as u16)]
    depth_edge_window: u16,
    /// Depth from focus by the classical focus measure, or by the seed's U-Nets through ONNX
    /// Runtime (scripts/setup-onnxruntime) at the pixels the classical stage trusts
    /// (docs/models.md).
    #[arg(long, value_enum, default_value_t = DepthMethodArg::Classic)]
    depth: DepthMethodArg,
    /// The depth model by name [default: the shipped one]; an installed one is
    /// `<models-dir>/<name>.onnx` with its card `<name>.json`.
    #[arg(long)]
    depth_model: Option<String>,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum DepthMethodArg {
    Classic,
    Cnn,
}

impl From<DepthArgs> for DepthOptions {
    fn from(args: DepthArgs) -> Self {
        Self {
            row_step: args.depth_row_step.into(),
            edge_window_radius_px: args.depth_edge_window.into(),
            method: match args.depth {
                DepthMethodArg::Classic => crestscan::pipeline::depth::DepthMethod::Classic,
                DepthMethodArg::Cnn => crestscan::pipeline::depth::DepthMethod::Cnn,
            },
            model: args.depth_model,
            ..Default::default()
        }
    }
}

/// Opens a bundle with the API 5B table; an error reads `[code] message`.
fn open_bundle(path: &Path, options: OpenOptions) -> Result<Bundle> {
    let bundle =
        Bundle::open(path, &ConnectionTable::api5b(), options).map_err(|e| anyhow::anyhow!("[{}] {e}", e.code()))?;
    if !bundle.unread_fields.is_empty() {
        eprintln!(
            "note: manifest.json has fields this crestscan does not read (accepted: a newer writer may add \
             optional fields): {}",
            bundle.unread_fields.join(", ")
        );
    }
    Ok(bundle)
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

/// An error as anyhow prints it (`Error: …` and its causes), without the backtrace.
pub fn error_text(error: &anyhow::Error) -> String {
    let mut text = format!("Error: {error}");
    let causes: Vec<String> = error.chain().skip(1).map(|c| c.to_string()).collect();
    match causes.as_slice() {
        [] => {}
        [one] => text.push_str(&format!("\n\nCaused by:\n    {one}")),
        many => {
            text.push_str("\n\nCaused by:");
            for (i, cause) in many.iter().enumerate() {
                text.push_str(&format!("\n    {i}: {cause}"));
            }
        }
    }
    text
}

pub fn main() -> Result<()> {
    let cli = Cli::parse();
    if !matches!(cli.command, Command::Serve(_) | Command::Healthcheck { .. }) {
        stop_quietly_on_closed_stdout();
    }
    match cli.command {
        Command::Simulate(args) => args.run(),
        Command::Inspect(args) => args.run(),
        Command::Bench(args) => args.run(),
        Command::Qualify(args) => args.run(),
        Command::Station(command) => command.run(),
        Command::Budget(args) => args.run(),
        Command::Compare(args) => args.run(),
        Command::Pairs(args) => args.run(),
        Command::Validate(args) => args.run(),
        Command::Connections(args) => args.run(),
        Command::Serve(args) => args.run(),
        Command::Keys(args) => args.run(),
        Command::MigrateStore(args) => args.run(),
        Command::WebhookSecret => {
            let secret = crestscan::service::webhooks::Secret::generate()
                .map_err(|e| anyhow::anyhow!("the operating system gave no random bytes: {e}"))?;
            println!("{secret}");
            Ok(())
        }
        Command::Openapi { manifest_schema: false } => {
            println!("{}", crestscan::service::api::openapi().to_pretty_json()?);
            Ok(())
        }
        Command::Openapi { manifest_schema: true } => {
            println!("{}", serde_json::to_string_pretty(&crestscan::service::api::schemas::manifest_schema())?);
            Ok(())
        }
        Command::Healthcheck { addr } => serve::healthcheck(addr),
    }
}

/// `options` with the pipeline options in the JSON file `path` written over them (the shape
/// `POST /v1/inspections` takes under `pipeline`; keys it leaves out keep their values).
pub fn options_over(
    options: crestscan::pipeline::PipelineOptions,
    path: Option<std::path::PathBuf>,
) -> anyhow::Result<crestscan::pipeline::PipelineOptions> {
    use anyhow::Context;
    let Some(path) = path else { return Ok(options) };
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let overrides: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
    let options =
        options.overridden_by(overrides).with_context(|| format!("{}: not pipeline options", path.display()))?;
    options.check_ranges().with_context(|| path.display().to_string())?;
    Ok(options)
}
