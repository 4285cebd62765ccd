"""The microlens grid from a white image and the 51-plane volumetric calibration. Not built
yet: see the calibration issue."""
