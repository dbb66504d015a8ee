//! Running blocking device-library calls (libusb, hidraw ioctls) off the async runtime.

use std::time::Duration;

use dioptra_core::LinkError;
use tokio::time::Instant;

/// Longest single blocking wait. A read with a long timeout is made of waits this short so
/// that a cancelled read frees the device within this time.
const SLICE: Duration = Duration::from_millis(50);

/// Runs `f` on tokio's blocking pool.
pub(crate) async fn run<T, F>(f: F) -> Result<T, LinkError>
where
    F: FnOnce() -> Result<T, LinkError> + Send + 'static,
    T: Send + 'static,
{
    tokio::task::spawn_blocking(f)
        .await
        .unwrap_or_else(|e| Err(LinkError::Io(format!("device I/O task failed: {e}"))))
}

/// Calls `attempt(wait)` on the blocking pool, with waits of at most [`SLICE`], until it
/// returns data or `timeout` has passed. `attempt` returns `Ok(None)` when its wait ended
/// with nothing. It is tried at least once, even with a zero timeout.
pub(crate) async fn read_in_slices<F>(timeout: Duration, attempt: F) -> Result<Vec<u8>, LinkError>
where
    F: Fn(Duration) -> Result<Option<Vec<u8>>, LinkError> + Clone + Send + 'static,
{
    let deadline = Instant::now() + timeout;
    loop {
        let wait = deadline
            .saturating_duration_since(Instant::now())
            .min(SLICE);
        let once = attempt.clone();
        if let Some(data) = run(move || once(wait)).await? {
            return Ok(data);
        }
        if Instant::now() >= deadline {
            return Err(crate::timeout_error(timeout));
        }
    }
}
