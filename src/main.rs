//! The `crestscan` binary: parses the command line and dispatches to [`cli`].

mod cli;

/// Prints a failed command's error and its causes, and a backtrace only when asked for with
/// `CRESTSCAN_BACKTRACE=1` (a `RUST_BACKTRACE` set for other programs no longer turns every error
/// into 45 lines of frames; panics still honour it).
fn main() -> std::process::ExitCode {
    let wanted = std::env::var_os("CRESTSCAN_BACKTRACE").is_some_and(|v| !v.is_empty() && v != "0");
    if wanted || std::env::var_os("RUST_LIB_BACKTRACE").is_none() {
        // SAFETY: set before any thread is started; only this process's error capture reads it.
        unsafe { std::env::set_var("RUST_LIB_BACKTRACE", if wanted { "1" } else { "0" }) };
    }
    match cli::main() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("{}", cli::error_text(&error));
            if wanted {
                eprintln!("\n{}", error.backtrace());
            }
            std::process::ExitCode::FAILURE
        }
    }
}
