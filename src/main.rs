//! `ufops`: the command line. It only parses arguments and wires the crates together.

mod cli;

use clap::Parser;

fn main() {
    keep_freed_memory_from_piling_up();
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
#[allow(unsafe_code, reason = "signal(2): std has no safe way to restore a default handler")]
fn restore_default_sigpipe() {
    #[cfg(unix)]
    // SAFETY: called once at start-up, before any other thread exists; SIG_DFL is a valid handler.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// glibc's malloc keeps up to 8 arenas per core and raises its mmap threshold each time a large
/// block is freed, so the megabyte buffers that exports, ingest and training allocate on tokio's
/// threads stay resident long after they are freed: exporting a 1.1 GB robomimic file peaked at
/// 460-585 MB of RSS over a 74 MB heap (heaptrack). One arena per core and a fixed 1 MiB mmap
/// threshold (a large buffer goes back to the system when freed) held it to 119 MB in the same
/// time (export/README.md, "Memory"). `MALLOC_ARENA_MAX` / `MALLOC_MMAP_THRESHOLD_` in the
/// environment still win.
#[allow(unsafe_code, reason = "mallopt(3): glibc's allocator has no safe interface")]
fn keep_freed_memory_from_piling_up() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get()).max(2);
        // SAFETY: called first in main, before any other thread exists; mallopt only sets the
        // allocator's parameters.
        unsafe {
            if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
                libc::mallopt(libc::M_ARENA_MAX, cores.min(64) as i32);
            }
            if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_none() {
                libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 20);
            }
        }
    }
}
