"""What measures the agents: evaluation folders and their records, metrics and statistics, comparisons, the
leaderboard and the rendered tables, sweeps and tuning, benchmarks, verification, and the tools that keep a results
folder whole (migrate, merge, drop). It imports the acting side (:mod:`bimp.agents`), never the CLI
(:mod:`bimp.agents.commands`)."""
