"""Learning to learn (Maximov et al. 2019, Sec. 3.3): a predictor network that reads one view of a
capture and outputs a DAM's weights. :mod:`model` (the network, its input, prediction),
:mod:`train` (training on a synth-set corpus, data-parallel), :mod:`file` (the predictor file
format and the predictor shipped in ``predictors/``)."""
