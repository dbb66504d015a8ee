# The workspace's version (Cargo.toml, [workspace.package]); a test keeps them equal.
__version__ = "0.1.0"
