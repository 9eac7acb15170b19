//! The `crestscan` binary: parses the command line and dispatches to [`cli`].

mod cli;

fn main() -> anyhow::Result<()> {
    cli::main()
}
