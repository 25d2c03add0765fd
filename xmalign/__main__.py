from xmalign.cli import main

main()
