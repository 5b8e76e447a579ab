"""What a DUT does beyond its calibration: offset stability, and (to come) frequency response,
perming, cross-field and thermal hysteresis (issue 37). No I/O: arrays in, figures out."""
