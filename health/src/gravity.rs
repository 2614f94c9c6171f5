//! Local gravity: a building's `g` with its standard uncertainty.
//!
//! Either measured (a gravimeter survey, a national gravity database: a value and its stated
//! uncertainty) or, by default, the normal gravity of the WGS84 ellipsoid at the site's latitude
//! (Somigliana's closed formula) taken to its height by the ellipsoid's second-order free-air
//! expansion (NIMA TR8350.2, eqs. 4-1 and 4-3).
//!
//! The normal formula describes the ellipsoid, not the Earth: the real `g` at a site departs from
//! it by the local anomaly. Its default standard uncertainty is stated from what that anomaly
//! can be, as independent parts:
//!
//! - free-air anomalies away from mountain ranges: 50 mGal (5·10⁻⁴ m/s²), their typical scale
//!   in continental lowlands (larger over ranges and trenches: give a measured value there);
//! - the mass between the ellipsoid and the site, which the free-air expansion ignores: a
//!   Bouguer plate of crustal density 2670 kg/m³ adds `2πGρ·h` = 0.1119 mGal per metre of
//!   height, counted whole as one standard uncertainty, since whether the site stands on a
//!   plateau (all of it) or on a tower over a plain (none) is not known here;
//! - a height given above sea level rather than above the ellipsoid: the geoid undulation,
//!   taken as 30 m (its global standard deviation), through the free-air gradient 0.3086 mGal/m.
//!
//! At 420 m that is 69 mGal (6.9·10⁻⁴ m/s², 7·10⁻⁵ of g).

use thiserror::Error;

/// Equatorial normal gravity of WGS84, m/s².
pub const GAMMA_EQUATOR_MPS2: f64 = 9.780_325_335_9;
/// Somigliana's constant k of WGS84.
const SOMIGLIANA_K: f64 = 0.001_931_852_652_41;
/// First eccentricity squared of WGS84.
const ECCENTRICITY_SQ: f64 = 0.006_694_379_990_13;
/// Semi-major axis of WGS84, m.
const SEMI_MAJOR_M: f64 = 6_378_137.0;
/// Flattening of WGS84.
const FLATTENING: f64 = 1.0 / 298.257_223_563;
/// ω²a²b/GM of WGS84.
const GEODETIC_M: f64 = 0.003_449_786_506_84;

/// Standard uncertainty of the normal formula from free-air anomalies, m/s² (50 mGal).
pub const ANOMALY_UNCERTAINTY_MPS2: f64 = 5e-4;
/// Attraction of a Bouguer plate per metre of height, 2πGρ with ρ = 2670 kg/m³, s⁻².
pub const BOUGUER_PER_M: f64 = 1.1196e-6;
/// Free-air gradient, s⁻².
pub const FREE_AIR_PER_M: f64 = 3.086e-6;
/// Standard deviation of the geoid undulation, m.
pub const GEOID_UNDULATION_M: f64 = 30.0;

/// What is wrong with a stated gravity.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum GravityError {
    #[error("latitude {0}° is not within −90° to 90°")]
    Latitude(f64),
    #[error("height {0} m is not within −500 m to 9000 m")]
    Height(f64),
    #[error("gravity {value_mps2} m/s² with standard uncertainty {uncertainty_mps2} m/s²: need 9.7 to 9.9 m/s² and an uncertainty above 0 and below 0.01 m/s²")]
    Value {
        value_mps2: f64,
        uncertainty_mps2: f64,
    },
}

/// A building's local gravity and its standard uncertainty (k = 1).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalGravity {
    pub value_mps2: f64,
    pub uncertainty_mps2: f64,
}

impl LocalGravity {
    /// A measured or looked-up value with its standard uncertainty.
    pub fn known(value_mps2: f64, uncertainty_mps2: f64) -> Result<LocalGravity, GravityError> {
        let ok =
            (9.7..=9.9).contains(&value_mps2) && uncertainty_mps2 > 0.0 && uncertainty_mps2 < 0.01;
        if !ok {
            return Err(GravityError::Value {
                value_mps2,
                uncertainty_mps2,
            });
        }
        Ok(LocalGravity {
            value_mps2,
            uncertainty_mps2,
        })
    }

    /// Normal gravity at geodetic latitude `latitude_deg` and height `height_m` (above the
    /// ellipsoid or sea level), with the uncertainty of the module's documentation.
    pub fn normal(latitude_deg: f64, height_m: f64) -> Result<LocalGravity, GravityError> {
        if !(-90.0..=90.0).contains(&latitude_deg) {
            return Err(GravityError::Latitude(latitude_deg));
        }
        if !(-500.0..=9000.0).contains(&height_m) {
            return Err(GravityError::Height(height_m));
        }
        let s2 = latitude_deg.to_radians().sin().powi(2);
        let surface =
            GAMMA_EQUATOR_MPS2 * (1.0 + SOMIGLIANA_K * s2) / (1.0 - ECCENTRICITY_SQ * s2).sqrt();
        let h = height_m;
        let value_mps2 = surface
            * (1.0
                - 2.0 / SEMI_MAJOR_M * (1.0 + FLATTENING + GEODETIC_M - 2.0 * FLATTENING * s2) * h
                + 3.0 * h * h / (SEMI_MAJOR_M * SEMI_MAJOR_M));
        let uncertainty_mps2 = (ANOMALY_UNCERTAINTY_MPS2.powi(2)
            + (BOUGUER_PER_M * h).powi(2)
            + (FREE_AIR_PER_M * GEOID_UNDULATION_M).powi(2))
        .sqrt();
        Ok(LocalGravity {
            value_mps2,
            uncertainty_mps2,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// WGS84's tabulated normal gravity at the equator and the pole (TR8350.2 Table 3.4:
    /// 9.7803253359 and 9.8321849378 m/s²), at 45° (9.806 197 769, evaluated by hand from
    /// Somigliana's formula), and the free-air decrease at 45°: 3.085·10⁻⁶ s⁻² near the surface.
    #[test]
    fn normal_gravity_matches_wgs84() {
        let eq = LocalGravity::normal(0.0, 0.0).unwrap();
        assert!((eq.value_mps2 - 9.780_325_335_9).abs() < 1e-10);
        let pole = LocalGravity::normal(90.0, 0.0).unwrap();
        assert!((pole.value_mps2 - 9.832_184_937_8).abs() < 1e-9);
        let mid = LocalGravity::normal(-45.0, 0.0).unwrap();
        assert!((mid.value_mps2 - 9.806_197_769_4).abs() < 1e-9);
        let high = LocalGravity::normal(45.0, 1000.0).unwrap();
        assert!((high.value_mps2 - 9.803_112_943_6).abs() < 1e-9);
        let gradient = (mid.value_mps2 - high.value_mps2) / 1000.0;
        assert!((gradient - 3.085e-6).abs() < 0.002e-6, "{gradient:e}");
    }

    /// At 420 m: √(50² + (0.11196·420)² + (0.3086·30)²) mGal = 69.26 mGal.
    #[test]
    fn uncertainty_by_hand_and_refusals() {
        let g = LocalGravity::normal(47.37, 420.0).unwrap();
        assert!((g.uncertainty_mps2 - 69.26e-5).abs() < 0.05e-5, "{g:?}");
        assert!(LocalGravity::normal(91.0, 0.0).is_err());
        assert!(LocalGravity::normal(0.0, f64::NAN).is_err());
        assert!(LocalGravity::known(9.81, 0.0).is_err());
        assert!(LocalGravity::known(f64::NAN, 1e-4).is_err());
        assert_eq!(
            LocalGravity::known(9.8067, 1e-5).unwrap().value_mps2,
            9.8067
        );
    }
}
