//! The gaze and photodiode tasks: forward every reading to the loop. A gaze sample goes
//! stamped with when it arrived; light edges (and reports of lost ones) go to the loop's hooks
//! (`dioptra hil`), the scheduler does not use them.

use std::future::Future;
use std::time::Instant;

use dioptra_core::{DeviceError, GazeSource, Photodiode};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use super::boxed::{BoxGaze, BoxPhotodiode};
use super::input::DeviceInput;
use super::link::{connect_retrying, Backoff, DeviceSettings, LinkHealth, Verdict};
use super::registry::DeviceHandle;

/// A device whose every reading is an input to the loop.
pub(crate) trait Forwarded: Send {
    fn next_input(&mut self) -> impl Future<Output = Result<DeviceInput, DeviceError>> + Send;
}

impl Forwarded for BoxGaze {
    async fn next_input(&mut self) -> Result<DeviceInput, DeviceError> {
        let s = self.next_sample().await?;
        Ok(DeviceInput::Gaze(s, Instant::now()))
    }
}

impl Forwarded for BoxPhotodiode {
    async fn next_input(&mut self) -> Result<DeviceInput, DeviceError> {
        Ok(DeviceInput::Light(self.next_light().await?))
    }
}

pub(crate) async fn forward_task<D, F, Fut>(
    mut connect: F,
    dev: DeviceHandle,
    settings: DeviceSettings,
    out: mpsc::Sender<DeviceInput>,
    stop: CancellationToken,
) where
    D: Forwarded,
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<D, DeviceError>>,
{
    let policy = settings.link;
    let mut backoff = Backoff::new(policy.backoff_min, policy.backoff_max);
    loop {
        let Some(mut d) = connect_retrying(&dev, &policy, &stop, &mut backoff, &mut connect).await
        else {
            return;
        };
        dev.ok();
        let mut health = LinkHealth::new(&policy);
        let lost = loop {
            let r = tokio::select! {
                _ = stop.cancelled() => return,
                r = d.next_input() => r,
            };
            match r {
                Ok(input) => {
                    health.ok();
                    if out.send(input).await.is_err() {
                        return;
                    }
                }
                Err(e) => match health.judge(&e) {
                    Verdict::Lost => break e,
                    Verdict::Keep => dev.error(&e),
                },
            }
        };
        dev.lost(&lost);
    }
}
