try:
    from lfpiv.cli import run
except KeyboardInterrupt:  # Ctrl-C while Python starts: nothing was done yet
    raise SystemExit(130) from None

run()
