"""The parts of a diagnosis against a held calibration (``--cal``, or the stated default for a
recording that covers a slice of the sphere): the held fit (:mod:`.fit`), the starting point
built on it (:mod:`.start`), the re-check at the fitted point (:mod:`.recheck`), the gyro link
that pins held parameters (:mod:`.gyro_pin`, :mod:`.gyro_guard`), the ranking subsample
(:mod:`.rank_subset`), the plausibility of an effect fitted on a slice (:mod:`.plausibility`)
and the auxiliary channels the residual follows (:mod:`.aux_channels`). The engine that uses
them is :mod:`streamcal.diagnosis.against`."""
