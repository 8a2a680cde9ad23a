"""The paper's tables (Maximov et al. 2019, Tables 1 and 2) as one harness: it sits above
appearance (the methods it scores) and synth (the held-out corpora it scores them on)."""
