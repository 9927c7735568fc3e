//! The `otofit` command line: the service, the pipeline and the studies (see `otofit --help`).

use clap::Parser;

fn main() {
    let cli = otofit::cli::Cli::parse();
    // Rust ignores SIGPIPE, so a closed pipe (`otofit … | head`) made println! panic. The
    // default action ends the process quietly, as other Unix tools do; not for the server,
    // which must outlive any client.
    #[cfg(unix)]
    if !matches!(cli.command, otofit::cli::Command::Serve(_) | otofit::cli::Command::Worker(_)) {
        // SAFETY: before any thread is started; SIG_DFL is a valid disposition.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
        // glibc serves blocks above a moving threshold (128 KiB at first) with fresh mmaps
        // and hands freed heap tops back to the kernel, so a training step's tensors (a
        // batch of 1000 × 50 floats is 200 KB) came back as page faults on zeroed pages:
        // 767,000 in a 30 s training, 3.1 s of system time; with fixed thresholds 11,000 and
        // 1.3 s (docs/results/npe.md). Not for the server, which would keep up to the
        // trim threshold per arena for its lifetime.
        #[cfg(target_env = "gnu")]
        // SAFETY: before any thread is started; both are documented mallopt parameters.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
            libc::mallopt(libc::M_TRIM_THRESHOLD, 128 << 20);
        }
    }
    if let Err(err) = otofit::cli::run(cli) {
        eprintln!("error: {err}");
        for cause in err.chain().skip(1) {
            eprintln!("  caused by: {cause}");
        }
        std::process::exit(1);
    }
}
