"""The long-running service: capture sources, processing threads, ZeroMQ publishing and control."""
