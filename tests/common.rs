//! Shared helpers of the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// The peer kit (`$TAPESTRY_PEERS`, else `../shared/peers` beside the workspace), if present.
pub fn peers_dir() -> Option<PathBuf> {
    let p = std::env::var_os("TAPESTRY_PEERS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/peers"));
    p.join("reference").is_dir().then_some(p)
}
