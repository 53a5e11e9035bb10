"""DF-VO inference from a checkout: the same as the installed ``dfvo-infer`` (:mod:`dfvo.cli.infer`)."""

from dfvo.cli.infer import main

if __name__ == "__main__":
    main()
