//! Optics methods (defocus, focal stacks, multifocal decomposition, retina, light fields, foveation, metrics) on CPU and wgpu backends. Filled by the renderer issue.
