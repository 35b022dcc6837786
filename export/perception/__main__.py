from export.perception.build import main

main()
