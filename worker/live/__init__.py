"""Live reconstruction: a job that follows a scan while it is recorded and publishes what it sees every few seconds."""
