//! The sans-IO scheduler coupling gaze to focus and time-multiplexing layers. Filled by the loop issue.
