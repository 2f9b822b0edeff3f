"""The terminal: what every layer's command line and long work share.

command_line.py holds the one-line-error parser, argument types, the result printer and
``bench``; progress.py the progress bar on standard error. Not a layer but the base under
all of them: it imports nothing else of vservo, and every layer may import it.
"""
