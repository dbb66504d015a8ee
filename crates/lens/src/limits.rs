//! The rig's safety limits, enforced in one place for every lens driver: a request outside
//! them is clamped or refused, as configured, and never sent.

use dioptra_core::{DeviceError, Diopters, PowerRange};

/// What to do with a request outside the limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum OutOfRange {
    /// Send the nearest allowed value instead.
    #[default]
    Clamp,
    /// Send nothing and return [`DeviceError::OutOfRange`].
    Refuse,
}

/// Limits of one rig's lens. Non-finite requests are always refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LensLimits {
    /// Powers the rig allows; the driver narrows this to what the device reports it reaches.
    pub power: PowerRange,
    /// Drive current bounds, mA (current mode; also programmed into devices that hold limits).
    pub current_ma: Option<(f32, f32)>,
    pub policy: OutOfRange,
}

impl LensLimits {
    pub fn new(power: PowerRange) -> Self {
        LensLimits {
            power,
            current_ma: None,
            policy: OutOfRange::Clamp,
        }
    }
    pub fn with_current_ma(mut self, min: f32, max: f32) -> Self {
        self.current_ma = Some((min, max));
        self
    }
    pub fn with_policy(mut self, policy: OutOfRange) -> Self {
        self.policy = policy;
        self
    }

    /// The rig's power range narrowed to `device`'s; an error when they do not overlap.
    pub fn narrowed_to(&self, device: PowerRange) -> Result<PowerRange, DeviceError> {
        let min = Diopters(self.power.min.0.max(device.min.0));
        let max = Diopters(self.power.max.0.min(device.max.0));
        PowerRange::new(min, max).ok_or_else(|| {
            DeviceError::Invalid(format!(
                "the rig's power range {}..={} D and the lens's reachable range {}..={} D do not \
                 overlap; check the rig configuration and the lens",
                self.power.min.0, self.power.max.0, device.min.0, device.max.0
            ))
        })
    }

    /// The power to send for a request of `requested` within `range`.
    pub fn check_power(
        &self,
        requested: Diopters,
        range: PowerRange,
    ) -> Result<Diopters, DeviceError> {
        check(
            "focal power (D)",
            requested.0,
            range.min.0,
            range.max.0,
            self.policy,
        )
        .map(Diopters)
    }

    /// The current to send for a request of `requested_ma`, within the rig's current limits
    /// and `hardware_max_ma` (the device's own maximum, either sign).
    pub fn check_current(
        &self,
        requested_ma: f32,
        hardware_max_ma: f32,
    ) -> Result<f32, DeviceError> {
        let (lo, hi) = self
            .current_ma
            .unwrap_or((-hardware_max_ma, hardware_max_ma));
        check(
            "current (mA)",
            requested_ma,
            lo.max(-hardware_max_ma),
            hi.min(hardware_max_ma),
            self.policy,
        )
    }
}

fn check(
    what: &'static str,
    v: f32,
    min: f32,
    max: f32,
    policy: OutOfRange,
) -> Result<f32, DeviceError> {
    // The request through the f32's shortest decimal form, so that 1.9 prints as 1.9, not
    // 1.900000095; the bounds (often computed in f32, e.g. a device's range: 6.4849997) to
    // 4 decimals, finer than any lens resolves.
    let wide = |x: f32| x.to_string().parse::<f64>().unwrap_or(f64::NAN);
    let bound = |x: f32| format!("{x:.4}").parse::<f64>().unwrap_or(f64::NAN);
    let refuse = || DeviceError::OutOfRange {
        what,
        requested: wide(v),
        min: bound(min),
        max: bound(max),
    };
    if !v.is_finite() || min.partial_cmp(&max).is_none_or(|o| o.is_gt()) {
        return Err(refuse());
    }
    if (min..=max).contains(&v) {
        return Ok(v);
    }
    match policy {
        OutOfRange::Clamp => Ok(v.clamp(min, max)),
        OutOfRange::Refuse => Err(refuse()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range(a: f32, b: f32) -> PowerRange {
        PowerRange::new(Diopters(a), Diopters(b)).unwrap()
    }

    #[test]
    fn clamp_and_refuse() {
        let clamp = LensLimits::new(range(0.0, 3.0));
        let refuse = clamp.with_policy(OutOfRange::Refuse);
        let r = clamp.power;
        assert_eq!(clamp.check_power(Diopters(4.0), r), Ok(Diopters(3.0)));
        assert_eq!(clamp.check_power(Diopters(-1.0), r), Ok(Diopters(0.0)));
        assert_eq!(refuse.check_power(Diopters(2.0), r), Ok(Diopters(2.0)));
        let e = refuse.check_power(Diopters(4.0), r).unwrap_err();
        assert!(e.to_string().contains("nothing was sent"), "{e}");
        // A range computed in f32 reads as the lens's figures.
        let device = range(-1.9000001, 6.4849997);
        let e = refuse.check_power(Diopters(9.0), device).unwrap_err();
        assert_eq!(
            e.to_string(),
            "focal power (D) 9 is outside the allowed range -1.9..=6.485; nothing was sent"
        );
        // NaN is never clamped into range.
        assert!(clamp.check_power(Diopters(f32::NAN), r).is_err());
    }

    #[test]
    fn narrowing_to_the_device() {
        let l = LensLimits::new(range(-1.0, 5.0));
        assert_eq!(l.narrowed_to(range(-2.0, 3.0)), Ok(range(-1.0, 3.0)));
        assert!(l.narrowed_to(range(6.0, 8.0)).is_err());
    }

    #[test]
    fn current_limits_and_hardware_max() {
        let l = LensLimits::new(range(0.0, 1.0)).with_current_ma(0.0, 200.0);
        assert_eq!(l.check_current(250.0, 292.84), Ok(200.0));
        assert_eq!(l.check_current(-5.0, 292.84), Ok(0.0));
        let open = LensLimits::new(range(0.0, 1.0)).with_policy(OutOfRange::Refuse);
        assert!(open.check_current(300.0, 292.84).is_err());
        assert_eq!(open.check_current(-100.0, 292.84), Ok(-100.0));
    }
}
