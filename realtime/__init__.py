"""The ring buffer and live pipeline feeding the monitor. Not built yet: see the live issue."""
