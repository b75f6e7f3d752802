"""Per frame: camera frame -> contacts. numpy and OpenCV only; no I/O, no clocks, no logging.

Everything here runs on the edge board for every frame, or builds what does
(the bundle's runtime objects). Offline code (scipy, scikit-learn) lives in
:mod:`optitac_edge.calibration`; devices and file formats in :mod:`optitac_edge.io`.
"""
