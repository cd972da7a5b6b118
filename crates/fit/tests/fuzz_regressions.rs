//! Regression tests for defects found by the cargo-fuzz targets (fuzz/FINDINGS.md).

use fit::residual::{ResidualMap, ResidualPoint};

/// fuzz/FINDINGS.md, calibration_file 1: `ResidualMap::eval` (and so `FieldModel::eval` and
/// `contains` of a RADIAL+RESIDUAL calibration) panicked inside spade at a NaN position
/// ("assertion failed: !f64::is_nan(pos.x)") and at |x| > 2^201 ("Failed to locate
/// position"). Such positions are outside the hull of the bins: `None`. Inside, the
/// natural-neighbour interpolant still passes through its data points.
#[test]
fn residual_map_at_unrepresentable_positions_is_none() {
    let pts: Vec<ResidualPoint> = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0), (0.4, 0.6)]
        .iter()
        .enumerate()
        .map(|(k, &(x, y))| ResidualPoint { x, y, dq: 1e-3 * k as f64, du: -2e-3 * k as f64 })
        .collect();
    let m = ResidualMap::new(pts.clone()).unwrap();
    for (x, y) in [
        (f64::NAN, 0.5),
        (0.5, f64::NAN),
        (f64::INFINITY, 0.5),
        (0.5, f64::NEG_INFINITY),
        (1e300, -1e300),
        (0.5, 1e61),
    ] {
        assert_eq!(m.eval(x, y), None, "({x}, {y})");
    }
    // Subnormal offsets from a vertex: the vertex's value (spade flushes them to 0).
    let (dq, du) = m.eval(1e-310, 0.0).unwrap();
    assert!((dq - pts[0].dq).abs() < 1e-15 && (du - pts[0].du).abs() < 1e-15);
    for p in &pts {
        let (dq, du) = m.eval(p.x, p.y).unwrap();
        assert!((dq - p.dq).abs() < 1e-12 && (du - p.du).abs() < 1e-12, "through ({}, {})", p.x, p.y);
    }
}
