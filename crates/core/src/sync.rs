//! Locking shared state across tasks and threads.

use std::sync::{Mutex, MutexGuard};

/// Locks `m`, also after a thread panicked while holding it. Every critical section in
/// dioptra leaves its data consistent before anything that can panic, so a poisoned lock's
/// data is still valid, and a panic elsewhere must not take the daemon's state down with it.
pub fn lock<T: ?Sized>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_poisoned_lock_still_gives_its_data() {
        let m = std::sync::Arc::new(Mutex::new(5));
        let m2 = m.clone();
        let _ = std::thread::spawn(move || {
            let _g = m2.lock().unwrap();
            panic!("poison it");
        })
        .join();
        assert!(m.is_poisoned());
        assert_eq!(*lock(&m), 5);
    }
}
