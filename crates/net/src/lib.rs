//! The DeepFocus-family network: architecture, weights, CPU and wgpu inference, training. Filled by the network issue.
