"""Studies: the speed/accuracy tradeoff and the independent references (analytic and NGSolve) it measures against."""
