use clap::Args;

#[derive(Args, Debug)]
pub struct SimulateArgs {
    /// Number of prior draws.
    #[arg(long)]
    pub n: Option<usize>,
}

pub fn run(_args: SimulateArgs) -> anyhow::Result<()> {
    anyhow::bail!("not yet implemented")
}
