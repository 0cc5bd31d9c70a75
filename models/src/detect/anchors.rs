//! The 896 SSD anchors of the short-range BlazeFace detector (MediaPipe
//! `SsdAnchorsCalculator`: 4 layers, strides 8, 16, 16, 16, fixed anchor size; kit README
//! step 2).

/// Input side of the detector tensor (pixels).
pub const DET_SIZE: usize = 128;
/// Number of anchors (and of detector output rows).
pub const NUM_ANCHORS: usize = 896;

/// `(grid cells across, anchors per cell)` of the merged layers: stride 8 (one layer, two
/// anchors per cell: aspect 1 and the interpolated one) and stride 16 (three layers merged,
/// six anchors per cell).
const GRIDS: [(usize, usize); 2] = [(DET_SIZE / 8, 2), (DET_SIZE / 16, 6)];

/// Anchor centres `(ax, ay)` in normalised tensor coordinates (0..1), in the detector's output
/// order: grid row outermost, then column, then the anchors of the cell. Anchor width and
/// height are 1 (`fixed_anchor_size`), so they do not appear.
pub fn ssd_anchors() -> Vec<[f64; 2]> {
    let mut out = Vec::with_capacity(NUM_ANCHORS);
    for (n, per_cell) in GRIDS {
        for y in 0..n {
            for x in 0..n {
                let c = [(x as f64 + 0.5) / n as f64, (y as f64 + 0.5) / n as f64];
                for _ in 0..per_cell {
                    out.push(c);
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anchor_count_and_layout_follow_the_readme() {
        let a = ssd_anchors();
        assert_eq!(a.len(), NUM_ANCHORS);
        // i < 512: cell i / 2 of the 16 x 16 grid.
        for (i, &[ax, ay]) in a.iter().enumerate().take(512) {
            let c = i / 2;
            assert_eq!(ax, ((c % 16) as f64 + 0.5) / 16.0);
            assert_eq!(ay, ((c / 16) as f64 + 0.5) / 16.0);
        }
        // i >= 512: cell (i - 512) / 6 of the 8 x 8 grid.
        for (i, &[ax, ay]) in a.iter().enumerate().skip(512) {
            let c = (i - 512) / 6;
            assert_eq!(ax, ((c % 8) as f64 + 0.5) / 8.0);
            assert_eq!(ay, ((c / 8) as f64 + 0.5) / 8.0);
        }
        assert_eq!(a[0], [1.0 / 32.0, 1.0 / 32.0]);
        assert_eq!(a[895], [15.0 / 16.0, 15.0 / 16.0]);
    }
}
