"""Command-line tools of semfeat_ros (console scripts)."""
