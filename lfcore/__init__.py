"""lfcore: pure light-field PIV computation (optics, rendering, reconstruction, vectors)."""
