//! UTC epochs as Julian dates, and the UTC -> TT offset the solar ephemeris needs.
//!
//! Invariant: a `UtcEpoch` always holds a valid Gregorian calendar date and time; the Julian date
//! is split into a whole-day part and a day fraction so sub-millisecond resolution survives.

use std::fmt;

/// TT - UTC in seconds (32.184 s + 37 leap seconds, valid since 2017-01-01). Earlier dates are
/// off by at most a few seconds, which moves the Sun by less than 0.001 deg.
pub(crate) const TT_MINUS_UTC_S: f64 = 69.184;
/// Julian date of the J2000.0 epoch (2000-01-01 12:00 TT).
pub(crate) const JD_J2000: f64 = 2_451_545.0;
const SECONDS_PER_DAY: f64 = 86_400.0;

/// A UTC calendar instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UtcEpoch {
    pub year: i32,
    pub month: u32,
    pub day: u32,
    pub hour: u32,
    pub minute: u32,
    pub second: f64,
}

/// Why a calendar date/time was rejected.
#[derive(Clone, Debug, PartialEq)]
pub struct EpochError(pub String);

impl fmt::Display for EpochError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "invalid epoch: {}", self.0)
    }
}

impl std::error::Error for EpochError {}

fn days_in_month(year: i32, month: u32) -> u32 {
    match month {
        1 | 3 | 5 | 7 | 8 | 10 | 12 => 31,
        4 | 6 | 9 | 11 => 30,
        _ => {
            let leap = (year % 4 == 0 && year % 100 != 0) || year % 400 == 0;
            if leap {
                29
            } else {
                28
            }
        }
    }
}

impl UtcEpoch {
    /// A validated epoch (years 1901..=2099, the range where the ephemeris is meaningful).
    pub fn new(
        year: i32,
        month: u32,
        day: u32,
        hour: u32,
        minute: u32,
        second: f64,
    ) -> Result<UtcEpoch, EpochError> {
        if !(1901..=2099).contains(&year) {
            return Err(EpochError(format!("year {year} outside 1901..=2099")));
        }
        if !(1..=12).contains(&month) {
            return Err(EpochError(format!("month {month} outside 1..=12")));
        }
        if day < 1 || day > days_in_month(year, month) {
            return Err(EpochError(format!(
                "day {day} does not exist in {year}-{month:02}"
            )));
        }
        if hour > 23 || minute > 59 || !(0.0..61.0).contains(&second) {
            return Err(EpochError(format!(
                "time {hour:02}:{minute:02}:{second} is not a valid UTC time"
            )));
        }
        Ok(UtcEpoch {
            year,
            month,
            day,
            hour,
            minute,
            second,
        })
    }

    /// Julian date (UTC scale) split as (whole days at 0h, fraction of day).
    pub(crate) fn julian_date_split(&self) -> (f64, f64) {
        // Meeus, Astronomical Algorithms ch. 7, Gregorian calendar.
        let (y, m) = if self.month <= 2 {
            (self.year - 1, self.month + 12)
        } else {
            (self.year, self.month)
        };
        let a = (y as f64 / 100.0).floor();
        let b = 2.0 - a + (a / 4.0).floor();
        let jd0 = (365.25 * (y as f64 + 4716.0)).floor()
            + (30.6001 * (m as f64 + 1.0)).floor()
            + self.day as f64
            + b
            - 1524.5;
        let fraction =
            (self.hour as f64 * 3600.0 + self.minute as f64 * 60.0 + self.second) / SECONDS_PER_DAY;
        (jd0, fraction)
    }

    /// Julian date on the UTC scale.
    pub fn julian_date_utc(&self) -> f64 {
        let (jd0, fraction) = self.julian_date_split();
        jd0 + fraction
    }

    /// Julian centuries of TT since J2000 at `offset_s` seconds after this epoch.
    pub(crate) fn centuries_tt_since_j2000(&self, offset_s: f64) -> f64 {
        let (jd0, fraction) = self.julian_date_split();
        let days = (jd0 - JD_J2000) + fraction + (offset_s + TT_MINUS_UTC_S) / SECONDS_PER_DAY;
        days / 36_525.0
    }

    /// ISO 8601 text of the instant `offset_s` seconds after this epoch, millisecond resolution.
    pub(crate) fn iso8601_after(&self, offset_s: f64) -> String {
        let (jd0, fraction) = self.julian_date_split();
        let total_ms = (fraction * SECONDS_PER_DAY * 1000.0).round() as i64
            + (offset_s * 1000.0).round() as i64;
        let day_ms = 86_400_000i64;
        let extra_days = total_ms.div_euclid(day_ms);
        let ms_of_day = total_ms.rem_euclid(day_ms);
        let (year, month, day) = calendar_from_jd0(jd0 + extra_days as f64);
        let hours = ms_of_day / 3_600_000;
        let minutes = (ms_of_day / 60_000) % 60;
        let seconds = (ms_of_day / 1000) % 60;
        let millis = ms_of_day % 1000;
        format!("{year:04}-{month:02}-{day:02}T{hours:02}:{minutes:02}:{seconds:02}.{millis:03}Z")
    }
}

/// Gregorian calendar date of a Julian date at 0h (Meeus ch. 7).
fn calendar_from_jd0(jd0: f64) -> (i64, u32, u32) {
    let z = (jd0 + 0.5).floor() as i64;
    let alpha = ((z as f64 - 1_867_216.25) / 36_524.25).floor() as i64;
    let a = z + 1 + alpha - alpha / 4;
    let b = a + 1524;
    let c = ((b as f64 - 122.1) / 365.25).floor() as i64;
    let d = (365.25 * c as f64).floor() as i64;
    let e = ((b - d) as f64 / 30.6001).floor() as i64;
    let day = (b - d - (30.6001 * e as f64).floor() as i64) as u32;
    let month = if e < 14 { e - 1 } else { e - 13 } as u32;
    let year = if month > 2 { c - 4716 } else { c - 4715 };
    (year, month, day)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn julian_date_of_known_instants() {
        // J2000.0 is 2000-01-01 12:00 (TT); Meeus example 7.a: 1957-10-04.81 = JD 2436116.31.
        let j2000 = UtcEpoch::new(2000, 1, 1, 12, 0, 0.0).unwrap();
        assert_eq!(j2000.julian_date_utc(), 2_451_545.0);
        let sputnik = UtcEpoch::new(1957, 10, 4, 19, 26, 24.0).unwrap();
        assert!((sputnik.julian_date_utc() - 2_436_116.31).abs() < 1e-6);
    }

    #[test]
    fn rejects_impossible_dates() {
        assert!(UtcEpoch::new(2023, 2, 29, 0, 0, 0.0).is_err());
        assert!(UtcEpoch::new(2024, 2, 29, 0, 0, 0.0).is_ok());
        assert!(UtcEpoch::new(2024, 13, 1, 0, 0, 0.0).is_err());
        assert!(UtcEpoch::new(2024, 1, 1, 24, 0, 0.0).is_err());
        assert!(UtcEpoch::new(2024, 1, 1, 0, 0, f64::NAN).is_err());
    }

    #[test]
    fn iso_text_rolls_over_days_and_years() {
        let epoch = UtcEpoch::new(2024, 12, 31, 23, 59, 58.0).unwrap();
        assert_eq!(epoch.iso8601_after(0.0), "2024-12-31T23:59:58.000Z");
        assert_eq!(epoch.iso8601_after(2.5), "2025-01-01T00:00:00.500Z");
        assert_eq!(
            epoch.iso8601_after(86_400.0 * 60.0),
            "2025-03-01T23:59:58.000Z"
        );
    }
}
