//! Whole-loop tests on simulated devices and the hardware-in-the-loop harness. Filled by the loop issue.
