"""Training from a checkout: the same as the installed ``dfvo-train`` (:mod:`dfvo.cli.train`)."""

from dfvo.cli.train import main

if __name__ == "__main__":
    main()
