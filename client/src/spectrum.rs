//! The discrete Fourier transform the consumers share (the alerting service's dominant
//! frequency, the console's spectra): one implementation, tested against the direct sum.

/// Iterative radix-2 Cooley–Tukey FFT of complex values `(re, im)` in place; `buf.len()` must
/// be a power of two (callers pad or choose their segment lengths so).
pub fn fft_in_place(buf: &mut [(f64, f64)]) {
    let n = buf.len();
    debug_assert!(n.is_power_of_two());
    let mut j = 0;
    for i in 1..n {
        let mut bit = n >> 1;
        while j & bit != 0 {
            j ^= bit;
            bit >>= 1;
        }
        j |= bit;
        if i < j {
            buf.swap(i, j);
        }
    }
    let mut len = 2;
    while len <= n {
        let angle = -2.0 * std::f64::consts::PI / len as f64;
        let (w_im, w_re) = angle.sin_cos();
        for start in (0..n).step_by(len) {
            let (mut cr, mut ci) = (1.0, 0.0);
            for k in 0..len / 2 {
                let (ar, ai) = buf[start + k];
                let (br, bi) = buf[start + k + len / 2];
                let (tr, ti) = (br * cr - bi * ci, br * ci + bi * cr);
                buf[start + k] = (ar + tr, ai + ti);
                buf[start + k + len / 2] = (ar - tr, ai - ti);
                (cr, ci) = (cr * w_re - ci * w_im, cr * w_im + ci * w_re);
            }
        }
        len <<= 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fft_matches_a_direct_dft() {
        for n in [1usize, 2, 16, 1024] {
            let x: Vec<(f64, f64)> = (0..n)
                .map(|i| {
                    (
                        (i as f64 * 0.7).sin() + 0.1 * i as f64,
                        (i as f64 * 0.3).cos(),
                    )
                })
                .collect();
            let mut fast = x.clone();
            fft_in_place(&mut fast);
            for (k, &(re, im)) in fast.iter().enumerate() {
                let (mut dr, mut di) = (0.0, 0.0);
                for (i, &(xr, xi)) in x.iter().enumerate() {
                    let (s, c) =
                        (-2.0 * std::f64::consts::PI * ((k * i) % n) as f64 / n as f64).sin_cos();
                    dr += xr * c - xi * s;
                    di += xr * s + xi * c;
                }
                let tol = 1e-9 * n as f64;
                assert!(
                    (re - dr).abs() < tol && (im - di).abs() < tol,
                    "n {n}, bin {k}"
                );
            }
        }
    }
}
