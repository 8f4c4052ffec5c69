"""Asyncio acquisition: schedules, arm and sensor backends, the scan runner and the control server."""
