//! Shared helpers of the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// The peer kit's scenes and reference arrays, vendored in `render-ops/tests/data/peers`
/// (`$TAPESTRY_PEERS` names another copy); a missing folder fails the test.
pub fn peers_dir() -> PathBuf {
    let p = std::env::var_os("TAPESTRY_PEERS")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("render-ops/tests/data/peers")
        });
    assert!(
        p.join("reference/hard_image.npy").is_file(),
        "peer reference data missing at {}",
        p.display()
    );
    p
}
