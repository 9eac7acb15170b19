//! `crestscan connections`: the API 5B table.

use anyhow::Result;
use crestscan::domain::thread::ConnectionTable;

#[derive(clap::Args)]
pub struct ConnectionsArgs {
    #[arg(long)]
    json: bool,
}

impl ConnectionsArgs {
    pub fn run(self) -> Result<()> {
        let table = ConnectionTable::api5b();
        if self.json {
            println!("{}", serde_json::to_string_pretty(table.all())?);
            return Ok(());
        }
        println!("designation\tfamily\tOD mm\tpitch mm\theight mm\tLc mm\tL4 mm");
        for c in table.all() {
            println!(
                "{}\t{}\t{:.2}\t{:.3}\t{:.3}\t{:.2}\t{:.2}",
                c.designation,
                c.family.as_str(),
                c.pipe_od_mm,
                c.pitch_mm,
                c.thread_height_mm,
                c.lc_mm,
                c.l4_mm
            );
        }
        Ok(())
    }
}
