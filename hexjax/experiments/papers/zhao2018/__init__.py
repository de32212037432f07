"""Zhao 2018: experiment 1 beside Table 2 (`table2`), the planner over random fields (`random_fields`), and
the planner steering the MJX robot among box obstacles (`closed_loop`)."""
