//! Wall and CPU time as the benchmarks and the timing examples measure them: one way of
//! measuring for all, so their figures compare.

use std::time::Instant;

/// The process's CPU time so far (user and system, all threads), ms: what work cost on a
/// machine shared with other work, where its wall time depends on that work. 0 off Unix.
pub fn process_cpu_ms() -> f64 {
    #[cfg(unix)]
    {
        // SAFETY: getrusage only writes the struct it is given, which is plain data.
        let mut u: libc::rusage = unsafe { std::mem::zeroed() };
        unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
        let ms = |v: libc::timeval| v.tv_sec as f64 * 1e3 + v.tv_usec as f64 * 1e-3;
        ms(u.ru_utime) + ms(u.ru_stime)
    }
    #[cfg(not(unix))]
    {
        0.0
    }
}

/// Runs `f` `runs` times (at least once): the wall time of each run in ms, fastest first, and
/// the last run's output. No warm-up: a caller that wants one runs `f` first.
pub fn wall_times_ms<T>(runs: usize, mut f: impl FnMut() -> T) -> (Vec<f64>, T) {
    let mut timed = || {
        let s = Instant::now();
        let out = f();
        (s.elapsed().as_secs_f64() * 1e3, out)
    };
    let (first, mut out) = timed();
    let mut t = vec![first];
    for _ in 1..runs {
        let (ms, o) = timed();
        t.push(ms);
        out = o;
    }
    t.sort_by(f64::total_cmp);
    (t, out)
}

/// The median wall time (ms) of `runs` runs of `f` after one warm-up run, and the last output.
pub fn median_wall_ms<T>(runs: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    f();
    let (t, out) = wall_times_ms(runs, f);
    (t[t.len() / 2], out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_run_is_timed_and_the_last_output_kept() {
        let mut n = 0;
        let (t, last) = wall_times_ms(4, || {
            n += 1;
            n
        });
        assert_eq!((t.len(), last), (4, 4));
        assert!(t.windows(2).all(|w| w[0] <= w[1]) && t[0] >= 0.0, "{t:?}");
        let mut n = 0;
        let (_, last) = median_wall_ms(3, || {
            n += 1;
            n
        });
        assert_eq!(last, 4, "one warm-up, then three timed runs");
        let (t, ()) = wall_times_ms(0, || ());
        assert_eq!(t.len(), 1, "at least one run");
    }

    #[test]
    fn cpu_time_grows_with_work() {
        let before = process_cpu_ms();
        let mut x = 0u64;
        for i in 0..20_000_000u64 {
            x = std::hint::black_box(x.wrapping_mul(31).wrapping_add(i));
        }
        std::hint::black_box(x);
        assert!(process_cpu_ms() > before, "{before}");
    }
}
