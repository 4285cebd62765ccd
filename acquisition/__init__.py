"""Device protocols, real drivers (GenICam cameras, pulse generator, stage), the PIV timing
plan, synchronised double-frame acquisition and the zarr recorder. Not built yet: see the
hardware issue."""
