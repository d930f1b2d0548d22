"""What the ECU firmware computes, as an executable reference: the calibration parameter block
(:mod:`.block`), the torque-ripple compensator (:mod:`.compensator`), the angle/speed estimator
and the golden vectors the firmware's unit tests consume.
"""
