"""Deep Appearance Maps (Maximov, Leal-Taixe, Fritz, Ritschel, ICCV 2019): model, fit, render,
baselines (RM, RM++) and evaluation (DSSIM)."""
