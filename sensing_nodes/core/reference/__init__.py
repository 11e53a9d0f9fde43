"""Reference (textbook) versions of production algorithms, for tests and teaching: nothing on the
robot runs these. Each is written the way a lesson writes it, and the tests check production
against it: wheel_odometry (the dead-reckoning step and its covariance as 3x3 products), lines
(split-and-merge with the polar least-squares fit, as numpy expressions and as plain loops)."""
