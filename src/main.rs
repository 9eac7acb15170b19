//! The `crestscan` binary: parses the command line and dispatches to [`cli`].

mod cli;

/// Prints a failed command's error and its causes, and a backtrace only when asked for with
/// `CRESTSCAN_BACKTRACE=1` (a `RUST_BACKTRACE` set for other programs no longer turns every error
/// into 45 lines of frames; panics still honour it).
fn main() -> std::process::ExitCode {
    few_malloc_arenas();
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

/// glibc gives a thread that meets a locked arena one of its own (up to 8 per core), and memory
/// freed into one arena is not reused by another: a worker's peak resident size fell by 15–35%
/// with `MALLOC_ARENA_MAX` set, at the same CPU time (docs/notebook/speed.md). Set by `mallopt`
/// from here it held no peak down, so the process starts itself again with the variable set (same
/// pid, arguments and streams): one arena per two cores. One already set is left as it is.
fn few_malloc_arenas() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
        use std::os::unix::process::CommandExt;
        let mut args = std::env::args_os();
        let Some(argv0) = args.next() else { return };
        let arenas = std::thread::available_parallelism().map_or(1, |n| (n.get() / 2).max(1));
        // `exec` returns only if it failed: then the process goes on with glibc's defaults.
        let _failed = std::process::Command::new("/proc/self/exe")
            .arg0(argv0)
            .args(args)
            .env("MALLOC_ARENA_MAX", arenas.to_string())
            .exec();
    }
}
