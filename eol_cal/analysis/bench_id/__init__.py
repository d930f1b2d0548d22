"""The bench identified at commissioning (``eol-cal bench identify``): a master motor's speed sweep
turned into points of the torque path's response (:mod:`.sweep`), the shaft line and transducer
fitted to them (:mod:`.identify`), the bench file and its plot written (:mod:`.output`)."""
