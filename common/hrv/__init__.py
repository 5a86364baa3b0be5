"""From an ECG to the windows the decision reads (paper §II-C): R peaks, cleaning and windows, annotated
records, the subject's calibration at rest, and the H10's GATT format."""
