//! dioptra's own lens controller over dioptra-protocol, on a CDC-ACM serial link or USB bulk
//! endpoints (any [`ByteLink`]). Requests, replies, refusals and clock synchronisation go
//! through the shared [`ProtocolClient`]; this driver adds the lens semantics, limits and
//! reconnection.

use std::sync::Arc;
use std::time::Duration;

use dioptra_core::{Clock, DeviceError, Diopters, LensState, PowerRange, Timestamp, VarifocalLens};
use dioptra_protocol::{Capabilities, DeviceInfo, DeviceKind, Limits, Message};
use dioptra_transport::protocol_client::{ProtocolClient, DEFAULT_REPLY_TIMEOUT};
use dioptra_transport::ByteLink;

use crate::limits::LensLimits;
use crate::reconnect::Opener;

/// Ping/pong rounds on connecting (PROTOCOL.md 7.1: a burst of 8).
pub const SYNC_BURST: usize = 8;
/// One more ping at most this often while the driver is used (PROTOCOL.md: once a second).
pub const SYNC_INTERVAL: Duration = Duration::from_secs(1);

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControllerConfig {
    pub limits: LensLimits,
    pub reply_timeout: Duration,
}

impl ControllerConfig {
    pub fn new(limits: LensLimits) -> Self {
        ControllerConfig {
            limits,
            reply_timeout: DEFAULT_REPLY_TIMEOUT,
        }
    }
}

/// One state reading with both clocks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControllerState {
    pub state: LensState,
    pub device_time_us: u64,
    /// The measurement's device time on the host timeline, once clocks are synchronised.
    pub measured_at: Option<Timestamp>,
}

/// A connected dioptra lens controller.
pub struct LensController<L: ByteLink> {
    client: ProtocolClient<L>,
    connected: bool,
    opener: Option<Opener<L>>,
    clock: Arc<dyn Clock>,
    cfg: ControllerConfig,
    info: Option<DeviceInfo>,
    device_limits: Option<Limits>,
    range: PowerRange,
    last_sync: Option<Timestamp>,
    /// The latest device time seen, a reference point for mapping host time to device time.
    last_device_us: Option<u64>,
    reconnects: u64,
}

impl<L: ByteLink> std::fmt::Debug for LensController<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LensController")
            .field("link", &self.client.link().describe())
            .field("info", &self.info)
            .field("range", &self.range)
            .finish_non_exhaustive()
    }
}

impl<L: ByteLink> LensController<L> {
    /// Opens a session on `link`. Without an [`Opener`] a lost link stays lost.
    pub async fn connect(
        link: L,
        cfg: ControllerConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, DeviceError> {
        let mut d = Self::new(link, None, cfg, clock);
        d.open_session().await?;
        Ok(d)
    }

    /// Opens the link with `opener` and keeps it to reopen the link after an unplug.
    pub async fn connect_with(
        mut opener: Opener<L>,
        cfg: ControllerConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, DeviceError> {
        let link = opener.open().await?;
        let mut d = Self::new(link, Some(opener), cfg, clock);
        d.open_session().await?;
        Ok(d)
    }

    fn new(
        link: L,
        opener: Option<Opener<L>>,
        cfg: ControllerConfig,
        clock: Arc<dyn Clock>,
    ) -> Self {
        LensController {
            client: ProtocolClient::new(link, clock.clone()).with_reply_timeout(cfg.reply_timeout),
            connected: true,
            opener,
            clock,
            range: cfg.limits.power,
            cfg,
            info: None,
            device_limits: None,
            last_sync: None,
            last_device_us: None,
            reconnects: 0,
        }
    }

    pub fn info(&self) -> Option<&DeviceInfo> {
        self.info.as_ref()
    }
    /// The limits the device reported at the last (re)connect.
    pub fn device_limits(&self) -> Option<Limits> {
        self.device_limits
    }
    pub fn is_connected(&self) -> bool {
        self.connected
    }
    pub fn reconnects(&self) -> u64 {
        self.reconnects
    }
    /// Device time on the host timeline, once clocks are synchronised.
    pub fn device_to_host(&self, device_time_us: u64) -> Option<Timestamp> {
        self.client.device_to_host(device_time_us)
    }
    /// Device clock rate error against the host's, ppm, once measurable.
    pub fn drift_ppm(&self) -> Option<f64> {
        self.client.clock_mapper().drift_ppm()
    }
    /// A device refusal of an earlier [`VarifocalLens::set_power`], which returns before the
    /// reply arrives.
    pub fn take_refusal(&mut self) -> Option<DeviceError> {
        self.client.take_unawaited_error()
    }

    /// Commands `power` to take effect at host time `at` (the device applies it on its own
    /// clock, so USB and OS latency do not shift it). Needs clocks in sync and a device with
    /// `SCHEDULED_APPLY`; `at` at most 1 s ahead. Returns when the command is on the wire.
    pub async fn set_power_at(
        &mut self,
        power: Diopters,
        at: Timestamp,
    ) -> Result<Timestamp, DeviceError> {
        self.ensure_session().await?;
        let power = self.cfg.limits.check_power(power, self.range)?;
        if !self
            .info
            .as_ref()
            .is_some_and(|i| i.capabilities.contains(Capabilities::SCHEDULED_APPLY))
        {
            return Err(DeviceError::Invalid(
                "this lens controller cannot schedule a power".into(),
            ));
        }
        let apply_at_us = self
            .host_to_device(at)
            .ok_or_else(|| DeviceError::Invalid("clocks are not synchronised yet".into()))?;
        let r = self.client.poll().await;
        self.note(r)?;
        let r = self
            .client
            .send(&Message::SetFocalPower {
                diopters: power.0,
                apply_at_us,
            })
            .await;
        self.note(r).map(|(_, t)| t)
    }

    /// Inverts the device-to-host mapping (linear, so two points give it exactly).
    fn host_to_device(&self, host: Timestamp) -> Option<u64> {
        let d0 = self.last_device_us?;
        let h0 = self.client.device_to_host(d0)?;
        let h1 = self.client.device_to_host(d0 + 1_000_000)?;
        let ns_per_us = (h1.signed_diff_ns(h0) as f64 / 1e6).max(1e-3);
        let d = d0 as f64 + host.signed_diff_ns(h0) as f64 / ns_per_us;
        // 0 means "on receipt" on the wire: never send it for a real instant.
        Some((d.max(1.0)) as u64)
    }

    /// Reads state with the device's timestamp mapped to host time.
    pub async fn state_detailed(&mut self) -> Result<ControllerState, DeviceError> {
        self.ensure_session().await?;
        let r = self.read_state().await;
        self.note(r)
    }

    async fn read_state(&mut self) -> Result<ControllerState, DeviceError> {
        self.keep_synced().await?;
        let r = self.client.request(&Message::GetLensState).await?;
        let Message::LensState(s) = r.message else {
            return Err(DeviceError::Protocol(format!(
                "expected LensState, device sent {:?}",
                r.message
            )));
        };
        self.last_device_us = Some(s.device_time_us);
        let measured = |v: f32| v.is_finite().then_some(v);
        Ok(ControllerState {
            state: LensState {
                power: Diopters(s.power_d),
                current_ma: measured(s.current_ma),
                temperature_c: measured(s.temperature_c),
                settled: Some(s.settled),
                host_time: r.host_time,
            },
            device_time_us: s.device_time_us,
            measured_at: self.client.device_to_host(s.device_time_us),
        })
    }

    /// One ping when the last is older than [`SYNC_INTERVAL`], so drift stays tracked.
    async fn keep_synced(&mut self) -> Result<(), DeviceError> {
        let has_sync = self
            .info
            .as_ref()
            .is_some_and(|i| i.capabilities.contains(Capabilities::TIME_SYNC));
        let now = self.clock.now();
        if has_sync
            && self
                .last_sync
                .is_none_or(|t| now.saturating_since(t) >= SYNC_INTERVAL)
        {
            self.client.sync_time(1).await?;
            self.last_sync = Some(now);
        }
        Ok(())
    }

    async fn open_session(&mut self) -> Result<(), DeviceError> {
        let r = self.session_setup().await;
        self.note(r)
    }

    async fn session_setup(&mut self) -> Result<(), DeviceError> {
        // PROTOCOL.md 5: a lone 0x00 first ends any garbage the device holds.
        self.client.link_mut().write_all(&[0]).await?;
        let info = self.client.hello().await?;
        if info.kind != DeviceKind::Lens || !info.capabilities.contains(Capabilities::FOCAL_POWER) {
            return Err(DeviceError::Invalid(format!(
                "{} is a {:?} without lens support, not a dioptra lens controller",
                self.client.link().describe(),
                info.kind
            )));
        }
        let r = self.client.request(&Message::GetLimits).await?;
        let Message::Limits(limits) = r.message else {
            return Err(DeviceError::Protocol(format!(
                "expected Limits, device sent {:?}",
                r.message
            )));
        };
        let device = PowerRange::new(Diopters(limits.min_power_d), Diopters(limits.max_power_d))
            .ok_or_else(|| {
                DeviceError::Protocol(format!("device reports unusable limits {limits:?}"))
            })?;
        self.range = self.cfg.limits.narrowed_to(device)?;
        let sync = info.capabilities.contains(Capabilities::TIME_SYNC);
        if sync {
            self.client.sync_time(SYNC_BURST).await?;
            self.last_sync = Some(self.clock.now());
        }
        self.device_limits = Some(limits);
        self.info = Some(info);
        self.last_device_us = None;
        if sync {
            // A device time to map from for scheduled powers.
            self.read_state().await?;
        }
        Ok(())
    }

    async fn ensure_session(&mut self) -> Result<(), DeviceError> {
        if self.connected {
            return Ok(());
        }
        let Some(opener) = self.opener.as_mut() else {
            return Err(DeviceError::Link(dioptra_core::LinkError::Disconnected(
                "the lens controller link was lost and this driver has no way to reopen it".into(),
            )));
        };
        let link = opener.open().await?;
        tracing::info!(link = %link.describe(), "lens controller reconnected");
        self.client.reset_session(link);
        self.connected = true;
        self.reconnects += 1;
        self.last_sync = None;
        self.open_session().await
    }

    fn note<T>(&mut self, r: Result<T, DeviceError>) -> Result<T, DeviceError> {
        if let Err(e) = &r {
            if e.needs_reconnect() {
                self.connected = false;
            }
        }
        r
    }
}

impl<L: ByteLink> VarifocalLens for LensController<L> {
    fn power_range(&self) -> PowerRange {
        self.range
    }

    async fn set_power(&mut self, power: Diopters) -> Result<Timestamp, DeviceError> {
        self.ensure_session().await?;
        let power = self.cfg.limits.check_power(power, self.range)?;
        // Take in replies to earlier sends (without waiting), so that a caller that only ever
        // sets powers does not leave them piling up until the link's buffers fill and stall.
        let r = self.client.poll().await;
        self.note(r)?;
        let r = self
            .client
            .send(&Message::SetFocalPower {
                diopters: power.0,
                apply_at_us: 0,
            })
            .await;
        self.note(r).map(|(_, t)| t)
    }

    async fn state(&mut self) -> Result<LensState, DeviceError> {
        self.state_detailed().await.map(|s| s.state)
    }
}
