"""The volcap command line, `volcap run` (the whole graph on a bag), the graph description, the node
table and the launch file."""
