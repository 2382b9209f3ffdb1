"""Images: EXR/PNG input and output, tonemapping, image metrics, plots and contact sheets.

NumPy, OpenEXR, Pillow and matplotlib only; depends on :mod:`._util`.
"""
