"""Everything that crosses the process boundary: the wire protocol, the subscriber client, and
every recording layout (Punyo .npy, PNG folder, MCAP) behind ``open_recording``."""
