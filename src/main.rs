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
    }
    if let Err(err) = otofit::cli::run(cli) {
        eprintln!("error: {err}");
        for cause in err.chain().skip(1) {
            eprintln!("  caused by: {cause}");
        }
        std::process::exit(1);
    }
}
