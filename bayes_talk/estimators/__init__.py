"""Estimators: one ``fit / predict / predict_dist / save / load`` protocol
(:mod:`bayes_talk.estimators.base`) implemented by the switching SGPDM, deena2009's SGPLVM
and every baseline, and the one registry of method families
(:mod:`bayes_talk.estimators.registry`)."""
