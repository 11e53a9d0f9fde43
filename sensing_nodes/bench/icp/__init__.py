"""The ICP benchmark, its dataset a parameter (`python -m sensing_nodes.bench.icp --help`):
datasets.py reads each dataset (scans, odometry guesses, references), scoring.py scores (pair
failures, ATE / RPE, CPU time), comparators.py holds the matchers compared (ours, the textbook
ICP, small_gicp, KISS-ICP); accuracy.py, speed.py and logs.py (the CARMEN logs through the
package's commands) measure, and `make bench` runs speed.run (area icp),
accuracy.run_kiss_area (icp_kiss) and speed.run_fast_lidar (icp_fast_lidar)."""
