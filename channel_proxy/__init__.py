"""The V2V medium process: control and data channels, TDMA, loss (issue 5)."""
