"""The lab: what reproduces the paper's comparisons and trains the shipped experts.

    python -m lab.baselines bc|gail|bc-gail ...   BC, GAIL and BC+GAIL (Sec. 5)
    python -m lab.ablations ...                   the ablations of Figure 4 (Sec. 5.3)
    python -m lab.experiments ...                 sweeps, figures and run diagnostics
    python -m lab.ars --env ...                   ARS V2-t experts (Hopper, HalfCheetah, Humanoid)
    python -m lab.sac --env ...                   SAC experts (Walker2d, Ant)
    python -m lab.table                           Table 1: random and expert returns
    python -m lab.benchmarks.update               one update's time against its GEMM floor

Beside them: optim.py (Adam, for SAC and the baselines) and shipping.py (what both expert
trainers share). Run from the repository root. The lab imports the core (offpac_il, nets,
expert, harness); the core never imports the lab.
"""
