//! The sync task: runs the plane schedule while the mode is multifocal, forwards its events,
//! and stops the sequence when the mode changes or the rig stops. With the rig's photodiode on
//! the board (`light`), it reads the board whatever the mode: the driver forwards the light.

use std::future::Future;

use dioptra_core::{DeviceError, PlaneSchedule, PlaneSequencer};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use super::input::DeviceInput;
use super::link::{connect_retrying, Backoff, DeviceSettings, LinkHealth, Verdict};
use super::registry::DeviceHandle;

/// What the sync task runs: the schedule while `multifocal` says so, and whether the rig's
/// photodiode is on the board (then the board is read in every mode).
pub(crate) struct SyncWork {
    pub schedule: PlaneSchedule,
    pub multifocal: watch::Receiver<bool>,
    pub light: bool,
}

pub(crate) async fn sync_task<S, F, Fut>(
    mut connect: F,
    dev: DeviceHandle,
    settings: DeviceSettings,
    work: SyncWork,
    out: mpsc::Sender<DeviceInput>,
    stop: CancellationToken,
) where
    S: PlaneSequencer,
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<S, DeviceError>>,
{
    let SyncWork {
        schedule,
        mut multifocal,
        light,
    } = work;
    let policy = settings.link;
    let mut backoff = Backoff::new(policy.backoff_min, policy.backoff_max);
    loop {
        let Some(mut s) = connect_retrying(&dev, &policy, &stop, &mut backoff, &mut connect).await
        else {
            return;
        };
        dev.ok();
        let mut health = LinkHealth::new(&policy);
        let mut running = false;
        // Program the schedule again after a reconnect if the mode wants it.
        multifocal.mark_changed();
        let lost: DeviceError = loop {
            tokio::select! {
                biased;
                _ = stop.cancelled() => {
                    if running {
                        if let Err(e) = s.stop().await {
                            dev.error(&e);
                        }
                    }
                    return;
                }
                r = multifocal.changed() => {
                    if r.is_err() {
                        stop.cancelled().await;
                        continue;
                    }
                    let want = *multifocal.borrow_and_update();
                    let r = if want && !running {
                        match s.program(&schedule).await {
                            Ok(()) => s.start().await,
                            Err(e) => Err(e),
                        }
                    } else if !want && running {
                        s.stop().await
                    } else {
                        Ok(())
                    };
                    match r {
                        Ok(()) => {
                            health.ok();
                            running = want;
                        }
                        Err(e) => match health.judge(&e) {
                            Verdict::Lost => break e,
                            Verdict::Keep => dev.error(&e),
                        },
                    }
                }
                r = s.next_event(), if running || light => match r {
                    Ok(ev) => {
                        health.ok();
                        let _ = out.try_send(DeviceInput::Sync(ev));
                    }
                    Err(e) => match health.judge(&e) {
                        Verdict::Lost => break e,
                        Verdict::Keep => dev.error(&e),
                    },
                },
            }
        };
        dev.lost(&lost);
    }
}
