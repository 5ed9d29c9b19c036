"""Exit statuses of ``youbot-fdi`` commands (documented in README and in each command's --help)."""
OK = 0  # done (faults found or not)
ERROR = 1  # a one-line reason on stderr: bad arguments, unreadable input, missing files
DAMAGED = 3  # a damaged recording (cut short, broken part-way): its readable part was analysed
INTERRUPTED = 130  # Ctrl-C
