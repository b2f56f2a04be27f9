"""Task definitions over the robot machinery: one locomotion task for any legged robot, and
the check that no single penalty rules a task's reward."""
