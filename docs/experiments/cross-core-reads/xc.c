#define _GNU_SOURCE
#include <stdio.h>
#include <pthread.h>
#include <stdatomic.h>
#include <time.h>
#include <string.h>
#define N (40*1024/8)
static long buf[N];
static atomic_int turn=0; static long sink;
static double now(){struct timespec t;clock_gettime(CLOCK_MONOTONIC,&t);return t.tv_sec*1e9+t.tv_nsec;}
static double tread[2]; 
void *worker(void*a){ // odd turns: read buffer written by main
  for(int r=0;r<2000;r++){ while(atomic_load(&turn)!=2*r+1); double t=now(); long s=0; for(int i=0;i<N;i++) s+=buf[i]; sink+=s; tread[1]+=now()-t; for(int i=0;i<N;i++) buf[i]=s+i; atomic_store(&turn,2*r+2);} return 0;}
int main(){pthread_t th; pthread_create(&th,0,worker,0);
  for(int r=0;r<2000;r++){ while(atomic_load(&turn)!=2*r); double t=now(); long s=0; for(int i=0;i<N;i++) s+=buf[i]; sink+=s; tread[0]+=now()-t; for(int i=0;i<N;i++) buf[i]=s-i; atomic_store(&turn,2*r+1);} pthread_join(th,0);
  double t=now(); long s=0; for(int r=0;r<2000;r++){for(int i=0;i<N;i++) s+=buf[i]; for(int i=0;i<N;i++) buf[i]=s+i;} double own=(now()-t)/2000;
  printf("read 40KB written by other core: %.2f us (main) %.2f us (worker); own read+write: %.2f us\n", tread[0]/2000/1e3, tread[1]/2000/1e3, own/1e3); return sink==1;}
