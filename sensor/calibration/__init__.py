"""Calibration: estimating a sensor profile from dark and flat-field spike recordings, the exact
statistics it inverts, and the derivation of the bundled ``vidar-default``.
"""
