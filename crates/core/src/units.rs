//! Units are types. Depth and focus are diopters in all optics code.

use std::fmt;
use std::ops::{Add, Neg, Sub};

macro_rules! unit {
    ($(#[$m:meta])* $name:ident, $suffix:literal) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, PartialOrd, Default)]
        #[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
        pub struct $name(pub f32);

        impl $name {
            pub const fn new(v: f32) -> Self {
                $name(v)
            }
            pub const fn value(self) -> f32 {
                self.0
            }
            pub fn is_finite(self) -> bool {
                self.0.is_finite()
            }
            pub fn abs(self) -> Self {
                $name(self.0.abs())
            }
            pub fn clamp(self, lo: Self, hi: Self) -> Self {
                $name(self.0.clamp(lo.0, hi.0))
            }
        }
        impl Add for $name {
            type Output = $name;
            fn add(self, o: $name) -> $name {
                $name(self.0 + o.0)
            }
        }
        impl Sub for $name {
            type Output = $name;
            fn sub(self, o: $name) -> $name {
                $name(self.0 - o.0)
            }
        }
        impl Neg for $name {
            type Output = $name;
            fn neg(self) -> $name {
                $name(-self.0)
            }
        }
        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                match f.precision() {
                    Some(p) => write!(f, "{:.*} {}", p, self.0, $suffix),
                    None => write!(f, "{} {}", self.0, $suffix),
                }
            }
        }
    };
}

unit!(
    /// Optical power or vergence, 1/m. Distance `d` metres is `1/d` diopters; 0 D is infinity.
    Diopters,
    "D"
);
unit!(
    /// Length in metres.
    Meters,
    "m"
);
unit!(
    /// Length in millimetres.
    Millimeters,
    "mm"
);

impl Diopters {
    /// The distance at which something at this vergence lies; infinite at 0 D.
    pub fn to_meters(self) -> Meters {
        Meters(1.0 / self.0)
    }
}

impl Meters {
    /// Vergence of a point this far away; 0 D for an infinite distance.
    pub fn to_diopters(self) -> Diopters {
        if self.0.is_infinite() {
            Diopters(0.0)
        } else {
            Diopters(1.0 / self.0)
        }
    }
    pub fn to_millimeters(self) -> Millimeters {
        Millimeters(self.0 * 1000.0)
    }
}

impl Millimeters {
    pub fn to_meters(self) -> Meters {
        Meters(self.0 / 1000.0)
    }
}

impl From<Millimeters> for Meters {
    fn from(v: Millimeters) -> Meters {
        v.to_meters()
    }
}

impl From<Meters> for Millimeters {
    fn from(v: Meters) -> Millimeters {
        v.to_millimeters()
    }
}

/// An inclusive range of optical power, e.g. what a lens may be driven to.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PowerRange {
    pub min: Diopters,
    pub max: Diopters,
}

impl PowerRange {
    /// `None` unless `min <= max` and both are finite.
    pub fn new(min: Diopters, max: Diopters) -> Option<Self> {
        (min.is_finite() && max.is_finite() && min.0 <= max.0).then_some(PowerRange { min, max })
    }
    pub fn contains(&self, p: Diopters) -> bool {
        p.0 >= self.min.0 && p.0 <= self.max.0
    }
    pub fn clamp(&self, p: Diopters) -> Diopters {
        p.clamp(self.min, self.max)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversions() {
        assert_eq!(Meters(0.5).to_diopters(), Diopters(2.0));
        assert_eq!(Meters(f32::INFINITY).to_diopters(), Diopters(0.0));
        assert_eq!(Diopters(4.0).to_meters(), Meters(0.25));
        assert_eq!(Millimeters(17.0).to_meters(), Meters(0.017));
        assert_eq!(Millimeters::from(Meters(0.004)), Millimeters(4.0));
        assert_eq!(format!("{:.1}", Diopters(1.25)), "1.2 D");
    }

    #[test]
    fn power_range() {
        assert!(PowerRange::new(Diopters(2.0), Diopters(1.0)).is_none());
        assert!(PowerRange::new(Diopters(f32::NAN), Diopters(1.0)).is_none());
        let r = PowerRange::new(Diopters(0.0), Diopters(3.0)).unwrap();
        assert!(r.contains(Diopters(3.0)));
        assert!(!r.contains(Diopters(3.01)));
        assert_eq!(r.clamp(Diopters(-1.0)), Diopters(0.0));
    }
}
