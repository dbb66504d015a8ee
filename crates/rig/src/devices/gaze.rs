//! The gaze task: forwards every sample to the loop, stamped with when it arrived.

use std::future::Future;
use std::time::Instant;

use dioptra_core::{DeviceError, GazeSource};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use super::{
    connect_retrying, Backoff, DeviceHandle, DeviceInput, DeviceSettings, LinkHealth, Verdict,
};

pub(crate) async fn gaze_task<G, F, Fut>(
    mut connect: F,
    dev: DeviceHandle,
    settings: DeviceSettings,
    out: mpsc::Sender<DeviceInput>,
    stop: CancellationToken,
) where
    G: GazeSource,
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<G, DeviceError>>,
{
    let policy = settings.link;
    let mut backoff = Backoff::new(policy.backoff_min, policy.backoff_max);
    loop {
        let Some(mut g) = connect_retrying(&dev, &policy, &stop, &mut backoff, &mut connect).await
        else {
            return;
        };
        dev.ok();
        let mut health = LinkHealth::new(&policy);
        let lost = loop {
            let r = tokio::select! {
                _ = stop.cancelled() => return,
                r = g.next_sample() => r,
            };
            match r {
                Ok(s) => {
                    health.ok();
                    if out
                        .send(DeviceInput::Gaze(s, Instant::now()))
                        .await
                        .is_err()
                    {
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
