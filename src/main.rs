//! `ufops`: the command line. It only parses arguments and wires the crates together.

mod cli;

use clap::Parser;

fn main() {
    let args = cli::Cli::parse();
    if !args.is_long_running() {
        restore_default_sigpipe();
    }
    let filter = tracing_subscriber::EnvFilter::try_from_env("UFOPS_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    let rt = match tokio::runtime::Builder::new_multi_thread().enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            std::process::exit(1);
        }
    };
    if let Err(e) = rt.block_on(cli::run(args)) {
        eprintln!("error: {}", one_line(&e));
        std::process::exit(1);
    }
}

/// An error as one clear line: its chain of causes, outermost first, leaving out a cause whose
/// text the line already holds (an error that prints its source, such as an I/O error naming its
/// file, would otherwise repeat `No such file or directory (os error 2)`).
fn one_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain().map(|c| c.to_string()) {
        if line.contains(&cause) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&cause);
    }
    line
}

/// Rust ignores SIGPIPE, so printing to a closed pipe (`ufops episodes | head`) panics. A
/// command-line tool should end quietly instead, as `cat` does. The server and the worker keep
/// SIGPIPE ignored: a client that hangs up must never kill them.
fn restore_default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: called once at start-up, before any other thread exists; SIG_DFL is a valid handler.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
