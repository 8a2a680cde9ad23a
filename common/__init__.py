"""The bottom of the house: what every stage shares. The capture-folder and EXR formats, errors,
atomic writes, numeric helpers, the one mesh type (:mod:`mesh`, :mod:`shapes`), the one ray
caster (:mod:`raycast`) and pinhole cameras (:mod:`cameras`).

Imports flow one way (``tests/test_layout.py`` holds the rule): common imports no stage; capture
imports common; reconstruct imports capture's decoders; appearance reads capture folders and
imports neither capture nor reconstruct; export uses appearance's model; synth (a producer of
capture folders) imports only common; the paper-table harness (paper) sits above appearance and
synth; cli sits on top.
"""
