//! The lens task: applies the newest commanded power, reads the lens back every
//! [`DeviceSettings::lens_poll`], reconnects a lost link, and parks the lens when the rig stops.

use std::future::Future;
use std::time::Duration;

use dioptra_core::{DeviceError, Diopters, VarifocalLens};
use serde::Serialize;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use super::input::{DeviceInput, LensId, LensOrder};
use super::link::{connect_retrying, Backoff, DeviceSettings, LinkHealth, Verdict};
use super::registry::DeviceHandle;

/// How the lens was left at shutdown.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParkReport {
    pub park_power: f32,
    /// Power the lens reported after parking, when it answered.
    pub reported_power: Option<f32>,
    pub error: Option<String>,
}

/// Serves the lens until `stop`, then parks it at `park`.
///
/// Commands come first: one waiting is sent before a poll starts, and one that arrives while
/// a state read is in flight cancels the read (dropping its future) and goes out at once, so
/// a command never waits behind a read. Drivers tolerate a dropped read: the Optotune driver
/// expects no reply to a set-power command and drains stray input before every exchange, and
/// the lens controller's client matches replies to requests by id.
///
/// After every (re)connect the newest commanded power is sent again before the lens is
/// reported up: a Lens Driver 4 resets its current on the session handshake, so without it
/// the lens would sit at its zero-current power until the next command.
#[allow(clippy::too_many_arguments)]
pub(crate) async fn lens_task<D, F, Fut>(
    mut connect: F,
    id: LensId,
    dev: DeviceHandle,
    settings: DeviceSettings,
    mut commands: watch::Receiver<Option<LensOrder>>,
    out: mpsc::Sender<DeviceInput>,
    park: Diopters,
    stop: CancellationToken,
) -> ParkReport
where
    D: VarifocalLens,
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<D, DeviceError>>,
{
    let policy = settings.link;
    let mut backoff = Backoff::new(policy.backoff_min, policy.backoff_max);
    loop {
        let Some(mut lens) =
            connect_retrying(&dev, &policy, &stop, &mut backoff, &mut connect).await
        else {
            return ParkReport {
                park_power: park.0,
                reported_power: None,
                error: Some("the lens was not connected at shutdown, so it was not parked".into()),
            };
        };
        let mut health = LinkHealth::new(&policy);
        let resend = *commands.borrow_and_update();
        if let Some(order) = resend {
            if let Err(e) = send(&mut lens, id, order, &out).await {
                dev.lost(&e);
                continue;
            }
        }
        dev.ok();
        let _ = out.send(DeviceInput::LensLink(id, true)).await;
        let mut poll = tokio::time::interval(settings.lens_poll);
        poll.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let lost = loop {
            tokio::select! {
                biased;
                _ = stop.cancelled() => {
                    return shut_down(&mut lens, id, &mut commands, &out, park, settings.park_timeout).await;
                }
                r = commands.changed() => {
                    if r.is_err() {
                        // The loop is gone: nothing more will be commanded.
                        stop.cancelled().await;
                        continue;
                    }
                    if let Err(e) = apply_newest(&mut lens, id, &mut commands, &out, &dev, &mut health).await {
                        break e;
                    }
                }
                _ = poll.tick() => {
                    // A command that arrives during the read preempts it: the read is dropped
                    // and the command goes out at once (see the doc of `lens_task`).
                    let read = tokio::select! {
                        biased;
                        _ = stop.cancelled() => {
                            return shut_down(&mut lens, id, &mut commands, &out, park, settings.park_timeout).await;
                        }
                        r = commands.changed() => {
                            if r.is_ok() {
                                if let Err(e) = apply_newest(&mut lens, id, &mut commands, &out, &dev, &mut health).await {
                                    break e;
                                }
                            }
                            continue;
                        }
                        r = lens.state() => r,
                    };
                    match read {
                        Ok(s) => {
                            health.ok();
                            let _ = out.try_send(DeviceInput::LensState(id, s));
                        }
                        Err(e) => match health.judge(&e) {
                            Verdict::Lost => break e,
                            Verdict::Keep => dev.error(&e),
                        },
                    }
                }
            }
        };
        dev.lost(&lost);
        let _ = out.send(DeviceInput::LensLink(id, false)).await;
    }
}

/// Sends `order` and reports it on the wire.
async fn send<D: VarifocalLens>(
    lens: &mut D,
    id: LensId,
    order: LensOrder,
    out: &mpsc::Sender<DeviceInput>,
) -> Result<dioptra_core::Timestamp, DeviceError> {
    let t = lens.set_power(order.power).await?;
    let host_path = order.caused_by_gaze.map(|at| at.elapsed());
    let _ = out.try_send(DeviceInput::LensWire {
        lens: id,
        id: order.id,
        requested: order.power,
        wire_time: t,
        host_path,
    });
    Ok(t)
}

/// Sends the newest commanded power; `Err` when the link is lost.
async fn apply_newest<D: VarifocalLens>(
    lens: &mut D,
    id: LensId,
    commands: &mut watch::Receiver<Option<LensOrder>>,
    out: &mpsc::Sender<DeviceInput>,
    dev: &DeviceHandle,
    health: &mut LinkHealth,
) -> Result<(), DeviceError> {
    let Some(order) = *commands.borrow_and_update() else {
        return Ok(());
    };
    match send(lens, id, order, out).await {
        Ok(_) => {
            health.ok();
            Ok(())
        }
        Err(e) => match health.judge(&e) {
            Verdict::Lost => Err(e),
            Verdict::Keep => {
                dev.error(&e);
                Ok(())
            }
        },
    }
}

/// The rig is stopping: the command the loop sent last (its own park) goes out, then the lens
/// is parked and watched until it reports the park power.
async fn shut_down<D: VarifocalLens>(
    lens: &mut D,
    id: LensId,
    commands: &mut watch::Receiver<Option<LensOrder>>,
    out: &mpsc::Sender<DeviceInput>,
    park: Diopters,
    timeout: Duration,
) -> ParkReport {
    if commands.has_changed().unwrap_or(false) {
        let pending = *commands.borrow_and_update();
        if let Some(order) = pending {
            // Reported like any command: the loop still reads inputs while devices stop.
            let _ = send(lens, id, order, out).await;
        }
    }
    park_lens(lens, park, timeout).await
}

/// Commands `park` and waits (up to `timeout`) until the lens reports it.
async fn park_lens<D: VarifocalLens>(
    lens: &mut D,
    park: Diopters,
    timeout: Duration,
) -> ParkReport {
    let mut report = ParkReport {
        park_power: park.0,
        reported_power: None,
        error: None,
    };
    if let Err(e) = lens.set_power(park).await {
        report.error = Some(format!("parking the lens failed: {e}"));
        return report;
    }
    let wait = async {
        loop {
            match lens.state().await {
                Ok(s) => {
                    report.reported_power = Some(s.power.0);
                    let close = (s.power.0 - park.0).abs() <= 0.02;
                    if close && s.settled != Some(false) {
                        return;
                    }
                }
                Err(e) => {
                    report.error = Some(format!("reading the parked lens failed: {e}"));
                    return;
                }
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    };
    if tokio::time::timeout(timeout, wait).await.is_err() {
        report.error = Some(format!(
            "the lens did not report {} D within {timeout:?} of the park command",
            park.0
        ));
    }
    report
}
