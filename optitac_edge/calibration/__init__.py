"""Offline, once per sensor: rest frames -> fiber map and surface operator; recordings with truth ->
calibration models; evaluation and reports. May use scipy and scikit-learn; never imported per frame.
"""
