//! `vlem plugins`: every implementation compiled into this binary, per stage.

use anyhow::Result;
use vlem_core::{Registry, StageKind};

/// Prints the registered implementations of each stage.
pub fn execute() -> Result<()> {
    let registry = Registry::global()?;
    for kind in StageKind::ALL {
        println!("{kind}s ([{}] kind = ...):", kind.section());
        let mut any = false;
        for r in registry.iter().filter(|r| r.builder.kind() == kind) {
            println!("  {:<16} {}", r.name, r.description);
            any = true;
        }
        if !any {
            println!("  (none compiled in)");
        }
    }
    Ok(())
}
