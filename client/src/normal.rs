//! The standard normal distribution function and its inverse, which the consumers share: the
//! alerting service's quantiles of a maximum of several normal errors, the console's χ²
//! bands. Tested against an independent implementation's values.

/// `Φ(x)`, the standard normal distribution function; relative error below 1.2·10⁻⁷ (the
/// Chebyshev fit of erfc in Numerical Recipes, §6.2), ample for coverage probabilities.
pub fn cdf(x: f64) -> f64 {
    0.5 * erfc(-x / std::f64::consts::SQRT_2)
}

fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let r = t * poly.exp();
    if x >= 0.0 {
        r
    } else {
        2.0 - r
    }
}

/// `Φ⁻¹(p)` for `p` in (0, 1); relative error below 1.2·10⁻⁹ (Acklam's rational
/// approximation). Infinite at 0 and 1, NaN outside.
pub fn quantile(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    const P_LOW: f64 = 0.024_25;
    if !(0.0..=1.0).contains(&p) {
        return f64::NAN;
    }
    if p == 0.0 {
        return f64::NEG_INFINITY;
    }
    if p == 1.0 {
        return f64::INFINITY;
    }
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < P_LOW {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - P_LOW {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// The point the largest of `n` independent standard normal variables exceeds with probability
/// `tail`: `Φ⁻¹((1 − tail)^(1/n))`, computed from the upper tail so that it stays exact for a
/// tail far below the precision of 1 − tail (k = 10 leaves 7.6·10⁻²⁴).
pub fn max_upper_quantile(tail: f64, n: usize) -> f64 {
    let per_variable = -((-tail).ln_1p() / n.max(1) as f64).exp_m1();
    -quantile(per_variable)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reference values from an independent implementation (SciPy's `norm.ppf`, `norm.cdf`).
    #[test]
    fn matches_reference_values() {
        for (p, z) in [
            (1e-10, -6.361_340_902_404_056),
            (0.001, -3.090_232_306_167_813),
            (0.024_25, -1.972_961_051_311_885),
            (0.1, -1.281_551_565_544_600_4),
            (0.5, 0.0),
            (0.8, 0.841_621_233_572_914_3),
            (0.975, 1.959_963_984_540_054),
            (0.999, 3.090_232_306_167_813),
            (1.0 - 1e-9, 5.997_807_019_601_637),
        ] {
            let got = quantile(p);
            assert!(
                (got - z).abs() <= 1e-8 * z.abs().max(1.0),
                "Φ⁻¹({p}) = {got}, not {z}"
            );
        }
        for (x, p) in [
            (-8.0, 6.220_960_574_271_74e-16),
            (-3.0, 0.001_349_898_031_630_093_3),
            (-1.5, 0.066_807_201_268_858_07),
            (0.0, 0.5),
            (0.5, 0.691_462_461_274_013_1),
            (2.0, 0.977_249_868_051_820_8),
            (4.0, 0.999_968_328_758_166_9),
        ] {
            let got = cdf(x);
            assert!((got - p).abs() <= 1.2e-7 * p, "Φ({x}) = {got}, not {p}");
        }
    }

    #[test]
    fn ends_and_the_maximum_of_many() {
        assert_eq!(quantile(0.0), f64::NEG_INFINITY);
        assert_eq!(quantile(1.0), f64::INFINITY);
        assert!(quantile(1.5).is_nan());
        // The largest of one is the variable itself; of ten, its 97.5 % point is Φ⁻¹(0.975^0.1).
        assert!((max_upper_quantile(0.025, 1) - 1.959_963_984_540_054).abs() < 1e-8);
        let p10: f64 = 0.975f64.powf(0.1);
        assert!((max_upper_quantile(0.025, 10) - quantile(p10)).abs() < 1e-8);
        assert!(max_upper_quantile(0.025, 10) > 2.7 && max_upper_quantile(0.025, 10) < 2.9);
        // A tail below f64's resolution near 1 still gives a finite point beyond it.
        let far = max_upper_quantile(cdf(-10.0), 5);
        assert!(far.is_finite() && far > 10.0 && far < 10.3, "{far}");
    }
}
