//! Where a cause's inversion has no answer, it says so with NaN instead of an identity that
//! reads as "no effect": a perfect polarizer's block leaves its retardance, rotation and
//! depolarization undetermined, and a plate's field basis from non-finite inputs is no basis.

use mueller::causes::{physical_of_block, tilted_hwp, UniaxialPlate};
use mueller::linear::physical_block;

#[test]
fn a_perfect_polarizer_leaves_the_rest_of_the_block_undetermined() {
    // Diattenuation 1 along Q (a perfect polarizer, the limit p -> 1 of eq:instpol): M_I has
    // rows (1, 1, 0), (1, 1, 0), (0, 0, 0) and no inverse.
    let p = physical_of_block(&physical_block(1.0, 0.0, [0.0, 0.0], 0.0, 0.0));
    assert_eq!((p[0], p[1]), (1.0, 0.0), "the diattenuation is row 0's");
    assert!(p[2..].iter().all(|v| v.is_nan()), "undetermined parts must be NaN, got {p:?}");
    // Just short of it the inversion holds and returns what the block was built from.
    let (g, rot, dep) = ([0.02, -0.01], 0.05, 0.01);
    let q = physical_of_block(&physical_block(0.9, 0.1, g, rot, dep));
    let want = [0.9, 0.1, g[0], g[1], rot, dep];
    for (k, (a, b)) in q.iter().zip(want).enumerate() {
        assert!((a - b).abs() < 1e-9, "parameter {k}: {a} for {b}");
    }
}

#[test]
fn a_plate_of_non_finite_incidence_gives_no_matrix() {
    // Quartz (n_o 1.5443, n_e 1.5534 at 589 nm; CRC Handbook) of one half-wave order.
    let plate = UniaxialPlate { n_o: 1.5443, n_e: 1.5534, thickness_waves: 0.5 / (1.5534 - 1.5443) };
    let m = tilted_hwp(&plate, 0.3, f64::NAN, 0.1);
    assert!(m.iter().all(|v| v.is_nan()), "{m}");
    // At normal incidence it is the half-wave retarder (the function's closed form).
    let n = tilted_hwp(&plate, 0.3, 0.0, 0.0);
    let r = mueller::retarder(std::f64::consts::PI, 0.3);
    assert!((n - r).abs().max() < 1e-9, "{n} vs {r}");
}
