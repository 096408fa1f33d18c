"""Learning in the cell: the policy learner and the pick-success score learner, their candidates,
versions and rollback."""
