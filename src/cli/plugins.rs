//! `vlem plugins`: every implementation compiled into this binary, per stage, with the cargo
//! feature of each optional one, and the optional ones this build lacks.

use anyhow::Result;
use vlem_core::{Registry, StageKind};

/// Prints the registered implementations of each stage.
pub fn execute() -> Result<()> {
    let registry = Registry::global()?;
    for kind in StageKind::ALL {
        println!("{kind}s ([{}] kind = ...):", kind.section());
        let mut any = false;
        for r in registry.iter().filter(|r| r.builder.kind() == kind) {
            let feature = registry
                .feature_of(kind, r.name)
                .map(|f| format!(" [feature `{f}`]"))
                .unwrap_or_default();
            println!("  {:<16} {}{feature}", r.name, r.description);
            any = true;
        }
        if !any {
            println!("  (none compiled in)");
        }
        let missing = registry.not_built(kind);
        if !missing.is_empty() {
            let missing: Vec<String> = missing
                .iter()
                .map(|(name, feature)| format!("{name} (feature `{feature}`)"))
                .collect();
            println!("  not in this build: {}", missing.join(", "));
        }
    }
    Ok(())
}
