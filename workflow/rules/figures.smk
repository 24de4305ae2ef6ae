# The paper's figures (results/figures/*.{png,pdf,csv}), drawn from result files only, and the `figures` target.
