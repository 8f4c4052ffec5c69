"""The lab's dashboard: a local web page that follows every scan under a captures root, the scan in hand, the
reconstruction queue and each reconstruction's preview, 3D view and report.

It stands above both halves, like the CLI: it reads capture folders (protocol's reader) and the queue (the worker's
read-only status view), and writes nothing. The daemon's own state is asked of the caller's `daemon_status` (the CLI
sends its control socket `spadscan ctl status`'s request, which the daemon answers as it answers ctl: it may read
the arm's speed slider to answer); the dashboard never talks to the arm itself.
"""
