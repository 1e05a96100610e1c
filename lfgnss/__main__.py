"""``python -m lfgnss``: list the commands."""
print("lfgnss commands:\n"
      "  python -m lfgnss.solve       position a RINEX file (EKF, factor graph or least squares)\n"
      "  python -m lfgnss.datasets    build benchmark datasets, check truth alignment and the coarse fix\n"
      "  python -m lfgnss.summary     feature statistics and plots per dataset\n"
      "  python -m lfgnss.benchmark   every estimator against RTKLIB on the test splits\n"
      "  python -m learning.train     train the LF-GNSS network")
