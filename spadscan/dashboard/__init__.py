"""The lab's dashboard: a local web page that follows every scan under a captures root, the scan in hand, the
reconstruction queue and each reconstruction's preview, 3D view and report.

It stands above both halves, like the CLI: it reads capture folders (protocol's reader) and the queue (the worker's
read-only status view), and never talks to the arm or writes anything.
"""
