"""The smallest command-line run of each tuner mode, shared by the tests of tuner runs and of interrupted runs."""

GRADIENT = ["tune", "--steps", "3", "--batch", "4", "--t-final", "5", "--n-attempts", "2000", "--tune", "k",
            "--validate", "0", "--no-progress"]
SEARCH = ["tune", "--search", "--steps", "3", "--batch", "8", "--population", "4", "--validate", "0", "--no-progress"]
FRONT = ["tune", "--pareto", "2", "--steps", "2", "--warm-steps", "1", "--batch", "4", "--t-final", "10",
         "--n-attempts", "1500", "--tune", "L,k", "--validate", "0", "--budgets", "5:50", "--no-progress"]
FRONT_VMAP = ["tune", "--pareto", "2", "--front-method", "vmap", "--steps", "3", "--batch", "4", "--t-final", "10",
              "--n-attempts", "1500", "--tune", "L,k", "--validate", "0", "--budgets", "5:50", "--no-progress"]
LAW = ["tune", "--controller", "astolfi", "--steps", "3", "--batch", "2", "--t-final", "2", "--validate", "0",
       "--no-progress"]

#: what differs between the files of two runs of the same settings to different --out names: the command line (the
#: wall time is in the sidecar FILE.run.json)
VOLATILE = {"command"}
