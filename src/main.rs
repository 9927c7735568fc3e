use clap::Parser;

fn main() {
    let cli = otofit::cli::Cli::parse();
    if let Err(err) = otofit::cli::run(cli) {
        eprintln!("error: {err}");
        for cause in err.chain().skip(1) {
            eprintln!("  caused by: {cause}");
        }
        std::process::exit(1);
    }
}
