//! `echosurf reconstruct`.

#[derive(Debug, clap::Args)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("`echosurf reconstruct` is not implemented yet")
}
