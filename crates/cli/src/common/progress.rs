//! Progress bars on stderr.

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};

/// A bar of `len` steps labelled `what`, with the time elapsed.
pub fn bar(len: usize, what: &str) -> Result<ProgressBar> {
    let pb = ProgressBar::new(len as u64);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} {elapsed_precise}")?
            .progress_chars("=> "),
    );
    pb.set_message(what.to_string());
    Ok(pb)
}
