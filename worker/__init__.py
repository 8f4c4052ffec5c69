"""Offline reconstruction: folder watcher, durable job queue, reconstruction, baselines, metrics and reports."""
