"""Gain tuning: constrained parametrizations (:mod:`jaxatt.fitting.parametrize`), the gains file
(:mod:`jaxatt.fitting.gainsfile`), the one fitter (:mod:`jaxatt.fitting.fitter`), the variance-free loss
(:mod:`jaxatt.fitting.varfree`) and the filtering floor it is compared with (:mod:`jaxatt.fitting.floor`)."""
